"""Fit the coefficients of o3dsoft.confidence on ModelNet40 train pairs (never the test split).

    python -m benchmarks.fit_confidence [--per-group 80] [--weights W] [--data D]

Each pair is aligned several times: by o3dsoft's network and ICP (search off: the result whose
confidence decides whether the search runs), by ICP from the ground truth turned by a random
rotation of up to 90 degrees, and by ICP from `--starts` rotations of any angle up to 180 degrees (the wrong
local minima among which the search must find the right one). The features of
o3dsoft.confidence are measured on each alignment, which is labelled a success when the rotation
error is below 5 degrees and the translation error below 0.05 x scale, and a logistic regression
is fitted (Newton's method, a small L2 penalty), successes and failures weighing equally in
total, so that 0.5 lies where the two kinds of error balance. Prints the coefficients to
paste into o3dsoft/confidence.py (ConfidenceConfig.coefficients), and the area under the ROC curve of the
confidence vs success on a held-out half (every other pair), per group and overall.

Groups: the protocols dcp, so3, rpmnet-crop, so3-crop and the independently sampled incongruent,
incongruent-noise and incongruent-crop; `unrelated` (source and target from two different shapes:
always a failure); `sparse` (dcp pairs whose target keeps a quarter of its points); `part` (a
source that is 30 % of the shape, cropped by a half-space, onto the whole shape).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from o3dsoft import confidence as conf
from o3dsoft import refine
from o3dsoft.bench import roc_auc
from o3dsoft.coarse import load_model
from o3dsoft.config import SearchConfig
from o3dsoft.data import _crop, get_protocol, load_pairs, make_pair
from o3dsoft.metrics import pair_errors
from o3dsoft.pipeline import RegisterConfig, register
from o3dsoft.transforms import quaternion_to_matrix, rigid

NAMES = conf.FEATURE_NAMES
PROTOCOLS = ("dcp", "so3", "rpmnet-crop", "so3-crop", "incongruent", "incongruent-noise", "incongruent-crop")


def make_problems(data: str, per_group: int, seed: int):
    """Yield (group, source, target, T_gt) from the train split."""
    for protocol in PROTOCOLS:
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


def random_rotation_within(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """A rotation about a uniform random axis by an angle uniform in [0, max_deg] degrees; (3, 3)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    half = np.radians(rng.uniform(0.0, max_deg)) / 2
    return quaternion_to_matrix(*(np.sin(half) * axis), np.cos(half))


def fit_logistic(X: np.ndarray, y: np.ndarray, l2: float = 1e-3, steps: int = 50, balanced: bool = True, failure_weight: float = 1.0) -> np.ndarray:
    """Logistic regression of y (N,) in {0, 1} on X (N, F): (F + 1,) intercept and weights. With
    `balanced`, each class weighs half of the total whatever its size; the failures (y = 0) weigh
    `failure_weight` times as much either way."""
    A = np.hstack([np.ones((len(X), 1)), X])
    sw = np.where(y > 0.5, 0.5 / max(y.mean(), 1e-12), 0.5 / max(1 - y.mean(), 1e-12)) if balanced else np.ones(len(y))
    sw = np.where(y > 0.5, sw, failure_weight * sw)
    w = np.zeros(A.shape[1])
    for _ in range(steps):
        p = 1 / (1 + np.exp(-A @ w))
        grad = A.T @ (sw * (p - y)) + l2 * w
        H = A.T @ (A * (sw * p * (1 - p))[:, None]) + l2 * np.eye(len(w))
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
    ap.add_argument("--rows", default=None, help="also write every alignment's features, label and group to this .npz")
    ap.add_argument("--starts", type=int, default=6, help="ICP runs per pair from random rotations of up to 180 degrees")
    args = ap.parse_args()
    model = load_model(args.weights)
    config = RegisterConfig(search=SearchConfig(mode="off"))
    rng = np.random.default_rng(args.seed)
    groups, X, y, pair_ids, far_off = [], [], [], [], []
    for n, (group, src, tgt, T_gt) in enumerate(make_problems(args.data, args.per_group, args.seed)):
        r = register(src, tgt, config, model=model)
        turns = [random_rotation_within(rng, 90.0)] + [random_rotation_within(rng, 180.0) for _ in range(args.starts)]
        icps = [refine.icp(src.astype(np.float64), tgt.astype(np.float64), T_gt @ rigid(R, np.zeros(3)), r.correspondence_distance, config.icp) for R in turns]
        scorer = conf.Scorer(src, tgt, r.correspondence_distance)
        for T in [r.transformation] + [icp.transformation for icp in icps]:
            e = pair_errors(T, T_gt)
            f = scorer(T)
            groups.append(group)
            X.append(conf.feature_vector(f))
            y.append(group != "unrelated" and e.rotation_deg < 5.0 and e.translation < 0.05 * r.scale)
            pair_ids.append(n)
            far_off.append(group == "unrelated" or e.rotation_deg > 15.0)
    groups, X, y, far_off = np.array(groups), np.array(X), np.array(y, dtype=bool), np.array(far_off)
    if args.rows:
        np.savez(args.rows, groups=groups, X=X, y=y, far_off=far_off, pair=np.array(pair_ids), names=np.array(NAMES))
    train = np.array(pair_ids) % 2 == 0  # all alignments of a pair on the same side
    w = fit_logistic(X[train], y[train].astype(float))
    score = 1 / (1 + np.exp(-(w[0] + X @ w[1:])))
    test = ~train
    report = {
        "coefficients": {"coefficients": [round(float(v), 4) for v in w], "features": ["intercept", *NAMES]},
        "pairs": int(len(y)),
        "success_rate": float(y.mean()),
        "auc_held_out": auc(score[test], y[test]),
        "flagged_correctly_held_out": float(np.mean((score[test] >= conf.ConfidenceConfig().likely_failed_below) == y[test])),
        "per_group": {},
    }
    for g in dict.fromkeys(groups):
        sel = test & (groups == g)
        report["per_group"][g] = {
            "pairs": int(sel.sum()),
            "success_rate": float(y[sel].mean()),
            "auc": auc(score[sel], y[sel]),
            "flagged_correctly": float(np.mean((score[sel] >= conf.ConfidenceConfig().likely_failed_below) == y[sel])),
            "right_ones_flagged": float(np.mean(score[sel & y] < conf.ConfidenceConfig().likely_failed_below)) if (sel & y).any() else None,
            "far_off_trusted": float(np.mean(score[sel & far_off] >= conf.ConfidenceConfig().likely_failed_below)) if (sel & far_off).any() else None,
        }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
