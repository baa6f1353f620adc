"""Fit the coefficients of o3dsoft.confidence on ModelNet40 train pairs (never the test split).

    python -m benchmarks.fit_confidence [--per-group 80] [--weights W] [--data D]

Registers pairs of several kinds with o3dsoft (network + ICP), measures the features of
o3dsoft.confidence on each result, labels it a success when the rotation error is below 5 degrees
and the translation error below 0.05 x scale, and fits a logistic regression (Newton's method, a
small L2 penalty). Prints the coefficients to paste into o3dsoft/confidence.py (INTERCEPT,
SLOPE), and the area
under the ROC curve of the confidence vs success on a held-out half, per group and overall.

Groups: the protocols dcp, so3, rpmnet-crop and so3-crop; `unrelated` (source and target from
two different shapes: always a failure); `sparse` (dcp pairs whose target keeps a quarter of its
points); `part` (a source that is 30 % of the shape, cropped by a half-space, onto the whole shape).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from o3dsoft import confidence as conf
from o3dsoft.bench import roc_auc
from o3dsoft.coarse import load_model
from o3dsoft.data import _crop, get_protocol, load_pairs, make_pair
from o3dsoft.metrics import pair_errors
from o3dsoft.pipeline import RegisterConfig, register

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "modelnet40_ply_hdf5_1024"
NAMES = ("consistency",)


def make_problems(data: str, per_group: int, seed: int):
    """Yield (group, source, target, T_gt) from the train split."""
    for protocol in ("dcp", "so3", "rpmnet-crop", "so3-crop"):
        ds = load_pairs(data, "train", get_protocol(protocol), seed)
        for i in np.linspace(0, len(ds) - 1, per_group).astype(int):
            p = ds[int(i)]
            yield protocol, p.source, p.target, p.transform
    ds = load_pairs(data, "train", get_protocol("dcp"), seed + 1)
    shapes = ds.shapes.points
    for n, i in enumerate(np.linspace(0, len(ds) - 1, per_group).astype(int)):
        rng = np.random.default_rng([seed, n])
        p = ds[int(i)]
        other = make_pair(shapes[(int(i) + 4919) % len(shapes)], get_protocol("dcp"), seed, int(i))
        yield "unrelated", p.source, other.target, p.transform
        keep = rng.choice(len(p.target), size=len(p.target) // 4, replace=False)
        yield "sparse", p.source, p.target[keep], p.transform
        yield "part", _crop(p.source.astype(np.float64), 0.3, rng).astype(np.float32), p.target, p.transform


def fit_logistic(X: np.ndarray, y: np.ndarray, l2: float = 1e-3, steps: int = 50) -> np.ndarray:
    A = np.hstack([np.ones((len(X), 1)), X])
    w = np.zeros(A.shape[1])
    for _ in range(steps):
        p = 1 / (1 + np.exp(-A @ w))
        grad = A.T @ (p - y) + l2 * w
        H = A.T @ (A * (p * (1 - p))[:, None]) + l2 * np.eye(len(w))
        w -= np.linalg.solve(H, grad)
    return w


def auc(score: np.ndarray, ok: np.ndarray) -> float:
    value = roc_auc(score, ok)
    return float("nan") if value is None else value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-group", type=int, default=80)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    model = load_model(args.weights)
    groups, X, y = [], [], []
    for group, src, tgt, T_gt in make_problems(args.data, args.per_group, args.seed):
        r = register(src, tgt, RegisterConfig(), model=model)
        e = pair_errors(r.transformation, T_gt)
        f = conf.features(src, tgt, r.transformation, r.correspondence_distance)
        groups.append(group)
        X.append([getattr(f, n) for n in NAMES])
        y.append(group != "unrelated" and e.rotation_deg < 5.0 and e.translation < 0.05 * r.scale)
    groups, X, y = np.array(groups), np.array(X), np.array(y, dtype=bool)
    train = np.arange(len(y)) % 2 == 0
    w = fit_logistic(X[train], y[train].astype(float))
    score = 1 / (1 + np.exp(-(w[0] + X @ w[1:])))
    test = ~train
    report = {"coefficients": {"INTERCEPT": round(float(w[0]), 4), "SLOPE": round(float(w[1]), 4)},
              "pairs": int(len(y)), "success_rate": float(y.mean()),
              "auc_held_out": auc(score[test], y[test]),
              "flagged_correctly_held_out": float(np.mean((score[test] >= conf.LIKELY_FAILED_BELOW) == y[test])),
              "per_group": {}}
    for g in dict.fromkeys(groups):
        sel = test & (groups == g)
        report["per_group"][g] = {"pairs": int(sel.sum()), "success_rate": float(y[sel].mean()), "auc": auc(score[sel], y[sel]),
                                  "flagged_correctly": float(np.mean((score[sel] >= conf.LIKELY_FAILED_BELOW) == y[sel]))}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
