"""Fit ConfidenceConfig.complete_coefficients on ModelNet40 train pairs (never the test split).

    python -m benchmarks.fit_complete_confidence [--per-protocol 80] [--data D] [--rows rows.npz]

Registers the first `--per-protocol` train pairs of each independently sampled protocol
(`incongruent`, `-noise`, `-so3`, `-crop`) with the shipped pipeline and keeps every estimate it
refined and scored (the networks', and the search's where it ran: the right pose and the wrong
local minima among which it chooses). On the pairs whose clouds both look complete, the estimates
whose pose shows no shared point (spacing ratio at least `independent_from`) are labelled right
(rotation error under 5 degrees, translation error under 0.05) or wrong, and a balanced logistic
regression on (consistency, overlap, spacing ratio) gives the coefficients to paste into
o3dsoft/confidence.py. Prints them, and the ROC AUC and false alarms (right estimates scored under
0.5) of a fit on every other pair, measured on the pairs it did not see.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from benchmarks.fit_confidence import auc, fit_logistic
from o3dsoft import confidence as conf
from o3dsoft import register, verify
from o3dsoft.data import get_protocol, load_pairs
from o3dsoft.metrics import pair_errors

PROTOCOLS = ("incongruent", "incongruent-noise", "incongruent-so3", "incongruent-crop")


def record(data: str, per_protocol: int):
    """(rows (K, 3) of COMPLETE_FEATURE_NAMES, right (K,), pair index (K,)) of every estimate
    scored on the complete-looking train pairs, whose pose shows no shared point."""
    kept = {}
    most_trusted = verify.Verifier.most_trusted

    def keep(self):  # the estimates of the pair being registered, at the moment the answer is chosen
        kept["attempts"], kept["complete"] = list(self.attempts), self.pair.complete
        return most_trusted(self)

    verify.Verifier.most_trusted = keep
    independent_from = conf.ConfidenceConfig().independent_from
    rows, right, pair_of = [], [], []
    try:
        for p_index, name in enumerate(PROTOCOLS):
            pairs = load_pairs(data, "train", get_protocol(name), 0)
            for i in range(min(per_protocol, len(pairs))):
                result = register(pairs[i].source, pairs[i].target)
                if not kept["complete"] or result.sparser_moved:  # the attempts of a swapped pair map target onto source
                    continue
                for a in kept["attempts"]:
                    f = a.scored
                    if f.spacing_ratio < independent_from:
                        continue
                    e = pair_errors(a.fine.transformation, pairs[i].transform)
                    rows.append(conf.complete_feature_vector(f))
                    right.append(e.rotation_deg < 5 and e.translation < 0.05)
                    pair_of.append(p_index * 100_000 + i)
            print(f"{name}: {len(rows)} estimates so far", flush=True)
    finally:
        verify.Verifier.most_trusted = most_trusted
    return np.array(rows, float), np.array(right, float), np.array(pair_of)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--per-protocol", type=int, default=80)
    ap.add_argument("--data", default=os.environ.get("O3DSOFT_DATA"))
    ap.add_argument("--rows", help="save the recorded estimates here (.npz), or load them when the file exists")
    args = ap.parse_args()
    if args.rows and os.path.exists(args.rows):
        z = np.load(args.rows)
        X, y, pair_of = z["X"], z["y"], z["pair"]
    else:
        X, y, pair_of = record(args.data, args.per_protocol)
        if args.rows:
            np.savez(args.rows, X=X, y=y, pair=pair_of)
    w = fit_logistic(X, y)
    print("complete_coefficients =", tuple(round(float(v), 2) for v in w), f"({len(y)} estimates, {int(y.sum())} right)")
    held = pair_of % 2 == 1
    w_half = fit_logistic(X[~held], y[~held])
    score = 1 / (1 + np.exp(-(w_half[0] + X[held] @ w_half[1:])))
    ok = y[held] > 0.5
    print(
        f"fit on the even pairs, measured on the odd ones: ROC AUC {auc(score, ok):.3f}, right estimates flagged {np.mean(score[ok] < 0.5):.1%}, wrong ones trusted {np.mean(score[~ok] >= 0.5):.1%}"
    )


if __name__ == "__main__":
    main()
