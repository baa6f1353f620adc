"""Before / after pictures of a registration that a person can judge it by.

Each panel is an orthographic view onto the target's principal plane (the plane of its two
largest principal axes: top-down for an outdoor scan, the main wall or floor of an indoor
fragment, the broad side of an object), drawn with Matplotlib's Agg canvas (no display needed).
The target is grey; the source is coloured by its distance to the target, so the overlap (dark)
and where it misfits (bright) show at a glance, whatever the scene's size.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np
from scipy.spatial import cKDTree

from .io import atomic_output
from .preprocess import principal_axes
from .transforms import apply_transform

_MAX_DRAWN = 20_000  # points per cloud and panel; more only slows the drawing down


def principal_plane(points: np.ndarray) -> np.ndarray:
    """(3, 2) the two largest principal axes of (N, 3) points, as columns (the view's x and y)."""
    return principal_axes(points)[:, :2]


def render_registration(
    path: Union[str, Path],
    source: np.ndarray,
    target: np.ndarray,
    panels: Sequence[Tuple[str, Optional[np.ndarray]]],
    distance: float,
    caption: str = "",
    dpi: int = 110,
) -> Path:
    """Write a PNG with one panel per (title, T_target_source) entry; None means the identity.

    Args:
        path: output .png path (written atomically).
        source: (N, 3); target: (M, 3), in the same units.
        panels: e.g. [("input", None), ("network", T_coarse), ("network + ICP", T_final)].
        distance: the colour scale's top, in cloud units: source points this far from the target
            or farther are drawn in the brightest colour (e.g. three cells of the voxel grid);
            each panel's title gives the share of the source within a third of it.
        caption: a line under the panels (errors, confidence).
    Returns:
        The path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rng = np.random.default_rng(0)
    src = source[rng.choice(len(source), min(len(source), _MAX_DRAWN), replace=False)]
    tgt = target[rng.choice(len(target), min(len(target), _MAX_DRAWN), replace=False)]
    tree = cKDTree(target)
    axes = principal_plane(tgt)
    origin = tgt.mean(axis=0)
    flat_tgt = (tgt - origin) @ axes

    fig = Figure(figsize=(4.2 * len(panels) + 0.8, 4.6))
    FigureCanvasAgg(fig)
    shown = None
    for i, (title, T) in enumerate(panels, start=1):
        moved = src if T is None else apply_transform(T, src)
        near, _ = tree.query(moved, distance_upper_bound=distance)  # inf beyond: drawn at the top of the scale, and far faster from a poor pose
        flat = (moved - origin) @ axes
        ax = fig.add_subplot(1, len(panels), i)
        ax.scatter(*flat_tgt.T, s=0.5, c="0.75", linewidths=0, label="target")
        shown = ax.scatter(*flat.T, s=0.7, c=np.minimum(near, distance), cmap="plasma", vmin=0.0, vmax=distance, linewidths=0, label="source")
        ax.set_aspect("equal")
        share = 100.0 * float(np.mean(near < distance / 3))
        ax.set_title(f"({chr(96 + i)}) {title}: {share:.0f} % of the source within {distance / 3:.3g} units", fontsize=8)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("along the plane's first axis (cloud units)", fontsize=6)
        if i == 1:
            ax.set_ylabel("along its second axis (cloud units)", fontsize=6)
            legend = ax.legend(loc="upper left", fontsize=7, markerscale=8)
            legend.legend_handles[1].set_color(shown.cmap(0.0))  # a near point's colour, not an arbitrary one
            legend.get_texts()[1].set_text("source (colour: distance)")
    fig.subplots_adjust(left=0.05, right=0.9, bottom=0.12, top=0.92, wspace=0.2)
    cbar = fig.colorbar(shown, ax=fig.axes, shrink=0.8, pad=0.01, extend="max")
    cbar.set_label(f"source point's distance to the target\n(cloud units, lower is better; from {distance:.3g}: the top colour)", fontsize=7)
    cbar.ax.tick_params(labelsize=6)
    fig.text(0.01, 0.01, "View: the target's principal plane. Shares of the source near the target: higher is better. " + caption, fontsize=7)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight", pad_inches=0.1)  # no margin left by the equal-aspect panels
    return Path(path)


def render_merged(path: Union[str, Path], points: np.ndarray, labels: np.ndarray, names: Sequence[str], caption: str = "", dpi: int = 110) -> Path:
    """Write a PNG of a merged cloud seen onto its principal plane, each scan in its own colour.

    Args:
        path: output .png path (written atomically).
        points: (P, 3) the scans in one frame; labels: (P,) each point's scan, an index into `names`.
        caption: a line under the picture.
    Returns:
        The path written.
    """
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rng = np.random.default_rng(0)
    keep = rng.choice(len(points), min(len(points), 4 * _MAX_DRAWN), replace=False)
    pts, lab = points[keep], labels[keep]
    flat = (pts - pts.mean(axis=0)) @ principal_plane(pts)
    fig = Figure(figsize=(7.5, 6.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    palette = colormaps["tab20"]
    for k, name in enumerate(names):
        mine = lab == k
        if mine.any():
            ax.scatter(*flat[mine].T, s=0.4, color=palette(k % 20), linewidths=0, label=Path(name).name)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=7, markerscale=12)
    ax.set_title("merged scans, one colour per scan", fontsize=9)
    fig.subplots_adjust(left=0.06, right=0.75, bottom=0.08, top=0.94)
    ax.set_xlabel("along the plane's first axis (cloud units)", fontsize=6)
    ax.set_ylabel("along its second axis (cloud units)", fontsize=6)
    fig.text(0.01, 0.01, "View: the merged cloud's principal plane. " + caption, fontsize=7)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight", pad_inches=0.1)
    return Path(path)
