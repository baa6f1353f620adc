"""Before / after pictures of a registration, like the paper's figures (a), (b), (c).

Rendered with Matplotlib's Agg canvas (no display needed): three 3-D scatter panels sharing one
view: the input pair, the source after the coarse stage, and after ICP.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from .io import atomic_output
from .transforms import apply_transform

_MAX_DRAWN = 4000  # points per cloud and panel; more only slows the drawing down


def render_registration(
    path: Union[str, Path],
    source: np.ndarray,
    target: np.ndarray,
    panels: Sequence[Tuple[str, Optional[np.ndarray]]],
    dpi: int = 110,
) -> Path:
    """Write a PNG with one panel per (title, T_target_source) entry; None means the identity.

    Args:
        path: output .png path (written atomically).
        source: (N, 3); target: (M, 3).
        panels: e.g. [("input", None), ("coarse", T_coarse), ("coarse + ICP", T_final)].
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rng = np.random.default_rng(0)
    src = source[rng.choice(len(source), min(len(source), _MAX_DRAWN), replace=False)]
    tgt = target[rng.choice(len(target), min(len(target), _MAX_DRAWN), replace=False)]
    moved = [(title, src if T is None else apply_transform(T, src)) for title, T in panels]
    allpts = np.vstack([tgt] + [m for _, m in moved])
    centre = (allpts.max(0) + allpts.min(0)) / 2
    half = (allpts.max(0) - allpts.min(0)).max() / 2

    fig = Figure(figsize=(4.2 * len(panels), 4.4))
    FigureCanvasAgg(fig)
    for i, (title, pts) in enumerate(moved, start=1):
        ax = fig.add_subplot(1, len(panels), i, projection="3d")
        ax.scatter(*tgt.T, s=0.6, c="black", alpha=0.55, label="target", depthshade=False)
        ax.scatter(*pts.T, s=0.6, c="tab:orange", alpha=0.55, label="source", depthshade=False)
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=20, azim=-60)
        ax.set_title(f"({chr(96 + i)}) {title}")
        ax.tick_params(labelsize=6)
        if i == 1:
            ax.legend(loc="upper left", fontsize=7, markerscale=8)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return Path(path)
