"""Fit the weights of the choice on partial overlaps (``SearchConfig.partial_choice``) on
ModelNet40 train pairs (never the test split).

    python -m benchmarks.fit_choice [--pairs 400 250 200] [--data D] [--records R.pkl] [--out F.json]

Each pair of the protocols incongruent-crop, so3-crop and rpmnet-crop (pairs spread evenly over
the train split, ``--pairs`` per protocol) is registered by the shipped pipeline with the learned
choice off, and every attempt's measurements are recorded with whether it is right (within 5
degrees and 0.05). Of the attempts the choice may take (those in contact, ``search.min_contact``)
of each pair whose clouds do not both look complete, a conditional logit is fitted: the
probability that attempt i is the right one is softmax_i(w . x_i) over the pair's attempts, with
x = (consistency, overlap, spacing ratio capped at 3, fitness_tight over the pair's most), by
maximum likelihood with an L2 penalty (pairs with no right attempt, or only right ones, carry no
information and are left out). Prints the weights to paste into ``SearchConfig.partial_choice``
and, per protocol, how many pairs the shipped choice and the fitted one get right, on the even
pairs when fitted on the odd ones and the other way round.
"""

from __future__ import annotations

import argparse
import pickle
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from benchmarks.eval_model import DEFAULT_DATA
from benchmarks.recorded import print_report, registered, right
from o3dsoft import verify
from o3dsoft.config import SearchConfig
from o3dsoft.pipeline import RegisterConfig

PROTOCOLS = ("incongruent-crop", "so3-crop", "rpmnet-crop")


def record(data: str, protocol: str, count: int, seed: int = 0) -> list:
    """Per pair: (X (A, 4) the measurements of the attempts the choice may take, y (A,) which are
    right, whether the shipped choice is right, whether the choice's rule applies)."""
    config = RegisterConfig(search=SearchConfig(partial_choice=None))
    rows = []
    for p, result, v in registered(data, protocol, count, config, seed):
        candidates = v.in_contact(v.attempts, config.search.min_contact)
        X = np.array([verify.choice_features(a, v.attempts) for a in candidates])
        y = np.array([right(a.fine.transformation, p.transform) for a in candidates])
        rows.append((X, y, right(result.transformation, p.transform), verify.choice_applies(v.pair)))
    return rows


def negative_log_likelihood(w: np.ndarray, rows: list, l2: float) -> float:
    total = 0.0
    for X, y, _, applies in rows:
        if not applies or not y.any() or y.all():
            continue
        s = X @ w
        total -= np.logaddexp.reduce(s[y]) - np.logaddexp.reduce(s)
    return total + l2 * float(w @ w)


def fit(rows: list, l2: float) -> np.ndarray:
    return minimize(negative_log_likelihood, np.zeros(4), args=(rows, l2), method="L-BFGS-B").x


def right_count(w: np.ndarray, rows: list) -> tuple:
    """(pairs, right by the shipped choice, right by the choice with weights w, right among the attempts)."""
    chosen = [bool(y[np.argmax(X @ w)]) if applies else now for X, y, now, applies in rows]
    return len(rows), sum(r[2] for r in rows), sum(chosen), sum(bool(r[1].any()) for r in rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--pairs", type=int, nargs=len(PROTOCOLS), default=[400, 250, 200], help="pairs per protocol: " + ", ".join(PROTOCOLS))
    ap.add_argument("--l2", type=float, default=0.1)
    ap.add_argument("--out", default=None, help="write the weights and the counts to this JSON file")
    ap.add_argument("--records", default=None, help="keep the recorded attempts in this .pkl file, and read them from it when it exists")
    args = ap.parse_args()
    if args.records and Path(args.records).exists():
        rows = pickle.loads(Path(args.records).read_bytes())
    else:
        rows = {protocol: record(args.data, protocol, count) for protocol, count in zip(PROTOCOLS, args.pairs)}
        if args.records:
            Path(args.records).write_bytes(pickle.dumps(rows))
    every = [r for protocol in PROTOCOLS for r in rows[protocol]]
    w = fit(every, args.l2)
    report = {"weights": dict(zip(("consistency", "overlap", "spacing_ratio", "contact"), np.round(w, 3).tolist())), "held_out": {}}
    for protocol in PROTOCOLS:
        even, odd = rows[protocol][0::2], rows[protocol][1::2]
        other = [r for p in PROTOCOLS if p != protocol for r in rows[p]]
        counts = [right_count(fit(other + train, args.l2), test) for train, test in ((odd, even), (even, odd))]
        report["held_out"][protocol] = dict(zip(("pairs", "shipped", "fitted", "among_attempts"), np.sum(counts, axis=0).tolist()))
    print_report(report, f"SearchConfig.partial_choice = {tuple(np.round(w, 2).tolist())}", args.out)


if __name__ == "__main__":
    main()
