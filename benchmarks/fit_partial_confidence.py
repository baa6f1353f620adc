"""Fit ``ConfidenceConfig.partial_coefficients`` on ModelNet40 train pairs (never the test split).

    python -m benchmarks.fit_partial_confidence [--pairs 400 250 200] [--data D] [--records R.pkl] [--out F.json]

Each pair of the protocols incongruent-crop, so3-crop and rpmnet-crop (pairs spread evenly over
the train split, ``--pairs`` per protocol) is registered by the pipeline with the partial
confidence off. Of each pair the choice on partial overlaps applies to
(:func:`o3dsoft.verify.choice_applies`), the result is recorded: whether it is right (within 5
degrees and 0.05), its strict confidence, its spacing ratio and overlap, and how many of the
pair's attempts reached its pose (:meth:`o3dsoft.verify.Verifier.agreeing`). The results the
partial confidence decides (pose with no shared point, the strict confidence flags it) are the
rows of a logistic regression on log(agreeing), a wrong result weighing ``--failure-weight`` right
ones. Prints the coefficients to paste into ``ConfidenceConfig.partial_coefficients`` and, per
protocol, the reported confidence's ROC AUC, right results flagged and wrong ones trusted without
it and with it (fitted on the other protocols and the other half of the pairs).
"""

from __future__ import annotations

import argparse
import math
import pickle
from dataclasses import replace
from pathlib import Path
from typing import List, NamedTuple

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from benchmarks.fit_confidence import auc, fit_logistic
from benchmarks.recorded import print_report, registered, right
from o3dsoft import confidence as conf
from o3dsoft import verify
from o3dsoft.pipeline import RegisterConfig

PROTOCOLS = ("incongruent-crop", "so3-crop", "rpmnet-crop")


class Record(NamedTuple):
    """One registered pair the choice on partial overlaps applies to."""

    right: bool  # the result lies within recorded.SUCCESS of the truth
    confidence: float  # the result's reported confidence, as registered
    strict: float  # its strict confidence
    spacing_ratio: float
    overlap: float
    agreeing: int  # attempts that reached its pose


def record(data: str, protocol: str, count: int, config: RegisterConfig, seed: int = 0) -> List[Record]:
    """The Record of each of `count` train pairs spread evenly over the split that the choice on
    partial overlaps applies to, registered with `config`."""
    rows = []
    for p, result, v in registered(data, protocol, count, config, seed):
        if not verify.choice_applies(v.pair) or result.sparser_moved:
            continue
        chosen = v.most_trusted()  # the attempt the result was refined from
        s = chosen.scored
        ok = right(result.transformation, p.transform)
        rows.append(Record(ok, result.confidence, conf.confidence(s, config.confidence), s.spacing_ratio, s.overlap, v.agreeing(chosen)))
    return rows


def decided(r: Record, config: conf.ConfidenceConfig) -> bool:
    """The partial confidence decides whether `r` is trusted: its pose shows no shared point, the
    clouds touch, and the strict confidence flags it."""
    return r.spacing_ratio >= config.independent_from and r.overlap >= config.min_overlap and r.strict < config.likely_failed_below


def fit(records: List[Record], config: conf.ConfidenceConfig, failure_weight: float) -> tuple:
    rows = [r for r in records if decided(r, config)]
    X = np.array([[math.log(r.agreeing)] for r in rows])
    y = np.array([r.right for r in rows], float)
    return tuple(np.round(fit_logistic(X, y, failure_weight=failure_weight), 2).tolist())


def reported(r: Record, config: conf.ConfidenceConfig) -> float:
    """The confidence `r`'s result reports under `config` (the larger of the strict and the
    partial one; the record's own where the partial one does not decide, or the geometry does
    not determine the pose: confidence 0)."""
    if config.partial_coefficients is None or not decided(r, config) or r.confidence == 0.0:
        return r.confidence
    f = conf.Features(0.0, 0.0, 0.0, r.overlap, r.spacing_ratio)
    return max(r.confidence, conf.partial_confidence(f, r.agreeing, config))


def summary(records: List[Record], scores: List[float], threshold: float) -> dict:
    """ROC AUC, right results flagged and wrong ones trusted (at `threshold`)."""
    ok, score = np.array([r.right for r in records]), np.array(scores)
    return {
        "pairs": len(records),
        "right": int(ok.sum()),
        "auc": round(auc(score, ok), 3),
        "right_flagged": round(float(np.mean(score[ok] < threshold)), 3) if ok.any() else None,
        "wrong_trusted": round(float(np.mean(score[~ok] >= threshold)), 3) if (~ok).any() else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--pairs", type=int, nargs=len(PROTOCOLS), default=[400, 250, 200], help="pairs per protocol: " + ", ".join(PROTOCOLS))
    ap.add_argument("--failure-weight", type=float, default=10.0, help="a wrong result weighs this many right ones")
    ap.add_argument("--out", default=None, help="write the coefficients and the held-out counts to this JSON file")
    ap.add_argument("--records", default=None, help="keep the records in this .pkl file, and read them from it when it exists")
    args = ap.parse_args()
    off = RegisterConfig(confidence=replace(conf.ConfidenceConfig(), partial_coefficients=None))
    if args.records and Path(args.records).exists():
        records = pickle.loads(Path(args.records).read_bytes())
    else:
        records = {protocol: record(args.data, protocol, count, off) for protocol, count in zip(PROTOCOLS, args.pairs)}
        if args.records:
            Path(args.records).write_bytes(pickle.dumps(records))
    c = off.confidence
    coefficients = fit([r for p in PROTOCOLS for r in records[p]], c, args.failure_weight)
    report = {
        "partial_coefficients": coefficients,
        "features": ["intercept", *conf.PARTIAL_FEATURE_NAMES],
        "failure_weight": args.failure_weight,
        "held_out": {},
    }
    for protocol in PROTOCOLS:
        halves = records[protocol][0::2], records[protocol][1::2]
        other = [r for p in PROTOCOLS if p != protocol for r in records[p]]
        tested, scores = [], []
        for train, test in ((halves[1], halves[0]), (halves[0], halves[1])):
            fitted = replace(c, partial_coefficients=fit(other + train, c, args.failure_weight))
            tested += test
            scores += [reported(r, fitted) for r in test]
        report["held_out"][protocol] = {
            "without": summary(tested, [r.confidence for r in tested], c.likely_failed_below),
            "with": summary(tested, scores, c.likely_failed_below),
            "decided": sum(decided(r, c) for r in tested),
        }
    print_report(report, f"ConfidenceConfig.partial_coefficients = {coefficients}", args.out)


if __name__ == "__main__":
    main()
