"""Train pairs registered by the pipeline, each with the :class:`o3dsoft.verify.Verifier` that
kept its attempts: what the scripts that fit the choice and the confidences record."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterator, Optional, Tuple

import numpy as np

from o3dsoft import verify
from o3dsoft.coarse import load_model
from o3dsoft.data import Pair, get_protocol, load_pairs
from o3dsoft.metrics import pair_errors
from o3dsoft.pipeline import RegisterConfig, RegistrationResult, register

# A pose is right within this rotation error (degrees) and translation error (shape units).
SUCCESS = (5.0, 0.05)


def registered(data: str, protocol: str, count: int, config: RegisterConfig, seed: int = 0) -> Iterator[Tuple[Pair, RegistrationResult, verify.Verifier]]:
    """(pair, result, verifier) of each of `count` train pairs of `protocol` spread evenly over
    the split (never the test split), registered with `config`."""
    model, search_model = load_model(config.weights, config.device), load_model(config.search.starts.weights, config.device)
    seen = []
    init = verify.Verifier.__init__

    def keep(self, *args, **kwargs):  # the verifier of each call, whose attempts are recorded
        init(self, *args, **kwargs)
        seen.append(self)

    verify.Verifier.__init__ = keep
    try:
        pairs = load_pairs(data, "train", get_protocol(protocol), seed)
        for i in np.linspace(0, len(pairs) - 1, count).astype(int):
            p = pairs[int(i)]
            seen.clear()
            result = register(p.source, p.target, config, model=model, search_model=search_model)
            yield p, result, seen[-1]
    finally:
        verify.Verifier.__init__ = init


def right(T: np.ndarray, truth: np.ndarray) -> bool:
    """The pose T (4, 4) lies within :data:`SUCCESS` of `truth` (4, 4)."""
    e = pair_errors(T, truth)
    return bool(e.rotation_deg < SUCCESS[0] and e.translation < SUCCESS[1])


def print_report(report: dict, paste: str, out: Optional[str]) -> None:
    """Print `report` as JSON and the line to paste into the config, and write the JSON to `out`."""
    print(json.dumps(report, indent=1))
    print(paste)
    if out:
        Path(out).write_text(json.dumps(report, indent=1) + "\n")
