"""The second network from the 24 rotations of a cube, replayed against the pipeline's result.

    python -m benchmarks.turned_starts [--protocol incongruent-so3 ...] [--count 150]
        [--split train] [--data PATH] [--out FILE.json]

For each of `count` pairs (spread over the split), registers the pair with
``second_network.turns=0`` and records whether the result is right and whether the search ran;
then runs the second network from each cube rotation (one pass each, the remaining passes on all
of them), refines and scores each estimate as the pipeline does (its reported confidence), and
records the fit after one pass. The report replays the rule of ``SecondNetworkConfig.turns``:
where the search ran, the best turned start (of the `keep` that fit best after one pass) ends it
when the complete confidence trusts it at ``ends_search`` and its odds are `odds` times those of
the pose as given; right results within (5 deg, 0.05) (higher is better), searches ended in
brackets. About 1.5 s per pair on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from typing import List

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from benchmarks.recorded import right
from o3dsoft import refine as refine_stage
from o3dsoft import search as search_stage
from o3dsoft.clock import StageClock
from o3dsoft.coarse import cached_model
from o3dsoft.data import get_protocol, load_pairs
from o3dsoft.pair import PreparedPair
from o3dsoft.pipeline import RegisterConfig, register
from o3dsoft.preprocess import denormalise_transform
from o3dsoft.verify import Verifier, _log_odds  # the odds the choice compares


def record(pair, config: RegisterConfig) -> dict:
    """The pipeline's result without turned starts, and every cube start's outcome, on one pair."""
    model = cached_model(config.weights, config.device)
    second = cached_model(config.second_network.weights, config.device)
    result = register(pair.source, pair.target, replace(config, second_network=replace(config.second_network, turns=0)), model=model)
    clock = StageClock()
    prepared = PreparedPair(pair.source, pair.target, config, model.config.k, ("source", "target"), clock)
    verifier = Verifier(prepared, clock)
    source, target = prepared.net_normalised
    estimates = search_stage.network_candidates(second, source, target, search_stage.cube_rotations())
    poses = [denormalise_transform(T, prepared.norm) for T in estimates]
    fit1 = [refine_stage.evaluate(*prepared.net, T, 0.5 * prepared.distance).fitness for T in poses]
    if config.second_network.iterations > 1:
        estimates = search_stage.network_candidates(second, source, target, estimates[:, :3, :3], config.second_network.iterations - 1)
    starts = []
    for T in estimates:
        pose = denormalise_transform(T, prepared.norm)
        attempt = verifier.add(pose, pose, "cube start")
        starts.append({"right": right(attempt.fine.transformation, pair.transform), "trust": verifier.reported(attempt).trust})
    return {"right": right(result.transformation, pair.transform), "searched": result.searched, "fit1": fit1, "starts": starts}


def replay(records: List[dict], keep: int, odds: float, ends: float) -> tuple:
    """(right, ended): the rule on the recorded pairs, start 0 being the pose as given."""
    hits = ended = 0
    for r in records:
        top = sorted(range(1, len(r["starts"])), key=lambda h: -r["fit1"][h])[:keep]
        best = max(top, key=lambda h: r["starts"][h]["trust"])
        trust, given = r["starts"][best]["trust"], r["starts"][0]["trust"]
        if r["searched"] and trust >= ends and _log_odds(trust) - _log_odds(given) >= math.log(odds):
            hits, ended = hits + r["starts"][best]["right"], ended + 1
        else:
            hits += r["right"]
    return hits, ended


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--protocol", nargs="+", default=["incongruent", "incongruent-noise", "incongruent-so3"])
    ap.add_argument("--count", type=int, default=150)
    ap.add_argument("--split", choices=["train", "test"], default="train")
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--out", help="write the records and the report here (JSON)")
    args = ap.parse_args()
    config = RegisterConfig()
    report = {}
    for name in args.protocol:
        pairs = load_pairs(args.data, args.split, get_protocol(name), 0)
        picks = np.linspace(0, len(pairs) - 1, args.count).astype(int) if args.split == "train" else range(min(args.count, len(pairs)))
        records = [record(pairs[int(i)], config) for i in picks]
        rows = {f"keep {k}, odds {o}": replay(records, k, o, config.second_network.ends_search) for k in (3, 4, 8, 23) for o in (1, 3, 5, 10)}
        report[name] = {"pairs": len(records), "pipeline right": sum(r["right"] for r in records), "replayed (right, ended)": rows, "records": records}
        print(name, len(records), "pairs; right without turned starts:", report[name]["pipeline right"])
        for label, (hits, ended) in rows.items():
            print(f"  {label:16s} right {hits:4d}  (search ended on {ended})")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
