"""Re-register, with the current code, the pairs of a bench run that failed or were flagged.

    python -m benchmarks.rerun_pairs RUN_DIR --protocol rpmnet-crop [--which failed|flagged|doubtful]
        [--max-rotation DEG] [--search-restart] [--search-feature-stop S] [--data D]

From RUN_DIR/pairs.csv (method ``o3dsoft``), `failed` takes the pairs beyond (5 deg, 0.05),
`flagged` the pairs within it whose confidence was below 0.5, `doubtful` every pair whose
confidence was at least 0.5 and below 0.9 (right or wrong). Each is registered again (the
shipped models, seed 0, as the bench does; give the run's --max-rotation if it had one), and
the counts within (1 deg, 0.01) and (5 deg, 0.05) (higher is better), of confident wrong
results (confidence >= 0.5 beyond (5 deg, 0.05); lower is better) and the median time per pair
(ms, lower is better) are printed for the run and for now. For a change that touches only the
hard pairs, this measures it in minutes instead of a whole-split run.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from o3dsoft.coarse import load_model
from o3dsoft.config import FeatureSearchConfig, RestartConfig, SearchConfig
from o3dsoft.data import get_protocol, load_pairs
from o3dsoft.metrics import pair_errors
from o3dsoft.pipeline import RegisterConfig, register


def outcome(rotation_deg: float, translation: float, confidence: float) -> np.ndarray:
    """(within 1 deg / 0.01, within 5 deg / 0.05, confident wrong) of one result."""
    right5 = rotation_deg < 5.0 and translation < 0.05
    return np.array([rotation_deg < 1.0 and translation < 0.01, right5, confidence >= 0.5 and not right5])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--protocol", required=True)
    parser.add_argument("--which", choices=("failed", "flagged", "doubtful"), default="failed")
    parser.add_argument("--max-rotation", type=float, default=None)
    parser.add_argument("--search-restart", action="store_true", help="search.restart.enabled = True")
    parser.add_argument("--search-feature-stop", type=float, default=0.5, help="search.features.stop")
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    args = parser.parse_args()

    rows = [r for r in csv.DictReader(open(args.run / "pairs.csv")) if r["method"] == "o3dsoft" and r["protocol"] == args.protocol]
    before = {int(r["index"]): (outcome(float(r["rotation_deg"]), float(r["translation"]), float(r["confidence"])), float(r["time_total_ms"])) for r in rows}
    confidence = {int(r["index"]): float(r["confidence"]) for r in rows}
    if args.which == "failed":
        chosen = [i for i, (o, _) in sorted(before.items()) if not o[1]]
    elif args.which == "flagged":
        chosen = [i for i, (o, _) in sorted(before.items()) if o[1] and confidence[i] < 0.5]
    else:
        chosen = [i for i in sorted(before) if 0.5 <= confidence[i] < 0.9]
    pairs = load_pairs(args.data, "test", get_protocol(args.protocol), 0)
    model, search_model = load_model(None, "cpu"), load_model("partial", "cpu")
    search = SearchConfig(features=FeatureSearchConfig(stop=args.search_feature_stop), restart=RestartConfig(enabled=args.search_restart))
    config = RegisterConfig(max_rotation=args.max_rotation, search=search)
    now, times = np.zeros(3, dtype=int), []
    for i in chosen:
        pair = pairs[i]
        result = register(pair.source.astype(np.float64), pair.target.astype(np.float64), config, model=model, search_model=search_model)
        e = pair_errors(result.transformation, pair.transform)
        now += outcome(e.rotation_deg, e.translation, result.confidence)
        times.append(result.timings_ms["total"])
    then = sum((before[i][0] for i in chosen), np.zeros(3, dtype=int))
    print(f"{args.protocol}, {len(chosen)} {args.which} pairs of {args.run}")
    print("             within 1 deg/0.01  within 5 deg/0.05  confident wrong  median ms")
    print(f"in the run   {then[0]:17d}  {then[1]:17d}  {then[2]:15d}  {np.median([before[i][1] for i in chosen]):9.0f}")
    print(f"now          {now[0]:17d}  {now[1]:17d}  {now[2]:15d}  {np.median(times):9.0f}")


if __name__ == "__main__":
    main()
