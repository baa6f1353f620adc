"""Real scans that overlap less and less: how often ``o3dsoft.register`` is right, and whether the
confidence flags what is wrong, against Open3D's FPFH + RANSAC + ICP.

    python -m benchmarks.partial_overlap [--data ../shared/data] [--levels 0.8 0.6 0.4 0.3 0.2]
        [--repeats 2] [--seed 0] [--out FILE.json]

The pairs: every known pair of real scans (3DMatch's five fragments, the laser pair, four bunny
pairs) brought into one frame, and four scans each split into two random halves (two independent
samplings of one surface). Each is cut `--repeats` times by two opposite half-spaces, one per cloud, so that about
`level` of each cloud's points has a partner in the other (within two point spacings); the source
is then turned by a uniform 0-180 degrees about a random axis and moved by about 0.3 x the scene
size. A result is right within 5 degrees and 5 % of the target's scene size (translation at the
source's centroid). Wrong results trusted are the dangerous ones (lower is better), right results
flagged the false alarms (lower is better). Run it alone on the machine: the times are its own.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
from scipy.spatial import cKDTree

LEVELS = (0.8, 0.6, 0.4, 0.3, 0.2)
RIGHT_DEG, RIGHT_SHARE = 5.0, 0.05  # a right result: within this rotation and this share of the scene size
PARTNER_SPACINGS = 2.0  # a point has a partner within this many point spacings of the other cloud
CUT_TRIES = 20  # cutting directions tried per pair and level
LEVEL_TOLERANCE = 0.05  # the overlap reached may miss the level by this much


def _spacing(points: np.ndarray) -> float:
    """Median distance from a point of the (N, 3) cloud to its nearest neighbour."""
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def bases(data: Path, rng: np.random.Generator) -> List[Tuple[str, str, np.ndarray, np.ndarray]]:
    """(name, kind, source in the target's frame (N, 3), target (M, 3)) per base pair; kind "pair"
    (two scans) or "halves" (one scan's two random halves)."""
    import o3dsoft
    from o3dsoft.scans import read_conf, relative_pose
    from o3dsoft.transforms import apply_transform

    kitchen, car, bunny = data / "real_scans" / "3dmatch_redkitchen", data / "real_scans" / "outdoor_laser_car", data / "stanford_bunny"
    found = []
    for s, t in ((4, 1), (6, 4), (6, 1), (21, 6), (34, 6), (34, 21)):
        T = o3dsoft.read_transform(kitchen / f"gt_{s}_to_{t}.txt")
        found.append((f"3dmatch {s}->{t}", "pair", apply_transform(T, o3dsoft.read_points(kitchen / f"cloud_bin_{s}.ply")), kitchen / f"cloud_bin_{t}.ply"))
    T = o3dsoft.read_transform(car / "gt_401_to_400.txt")
    found.append(("laser 401->400", "pair", apply_transform(T, o3dsoft.read_points(car / "car_cloud401.ply")), car / "car_cloud400.ply"))
    poses = read_conf(bunny / "bun.conf")
    for s, t in (("bun045", "bun000"), ("bun315", "bun000"), ("bun090", "bun045"), ("chin", "bun000")):
        T = relative_pose(poses, f"{s}.ply", f"{t}.ply")
        found.append((f"bunny {s}->{t}", "pair", apply_transform(T, o3dsoft.read_points(bunny / f"{s}.ply")), bunny / f"{t}.ply"))
    out = [(name, kind, source, o3dsoft.read_points(target)) for name, kind, source, target in found]
    for name, path in (
        ("3dmatch 1", kitchen / "cloud_bin_1.ply"),
        ("3dmatch 21", kitchen / "cloud_bin_21.ply"),
        ("laser 400", car / "car_cloud400.ply"),
        ("bunny 000", bunny / "bun000.ply"),
    ):
        points = o3dsoft.read_points(path)
        half = rng.random(len(points)) < 0.5
        out.append((f"{name} halves", "halves", points[half], points[~half]))
    return [(name, kind, s[np.isfinite(s).all(axis=1)], t[np.isfinite(t).all(axis=1)]) for name, kind, s, t in out]


def cut(source: np.ndarray, target: np.ndarray, level: float, rng: np.random.Generator) -> Optional[Tuple[np.ndarray, np.ndarray, float]]:
    """The (N', 3) source below and the (M', 3) target above a plane each, along one random
    direction (every other try within a ball about a point the two share first, so that pairs
    that overlap little can reach a high level), so that about `level` of each kept cloud has a
    partner in the other; and the overlap reached (the smaller of the two shares). None where no
    try comes within :data:`LEVEL_TOLERANCE` of it."""
    from o3dsoft.preprocess import scene_size

    radius = PARTNER_SPACINGS * max(_spacing(source), _spacing(target))
    shared = np.flatnonzero(np.isfinite(cKDTree(target).query(source, distance_upper_bound=radius)[0]))
    size = max(scene_size(source), scene_size(target))
    best: Optional[Tuple[float, np.ndarray, np.ndarray, float]] = None
    for attempt in range(CUT_TRIES):
        s_in, t_in = np.ones(len(source), bool), np.ones(len(target), bool)
        if attempt % 2 and len(shared):
            centre, reach = source[rng.choice(shared)], rng.uniform(0.3, 0.8) * size
            s_in, t_in = np.linalg.norm(source - centre, axis=1) < reach, np.linalg.norm(target - centre, axis=1) < reach
        found = _cut_along(source[s_in], target[t_in], radius, level, rng)
        if found is not None and (best is None or found[0] < best[0]):
            best = found
        if best is not None and best[0] < LEVEL_TOLERANCE / 2:
            break
    if best is None or best[0] > LEVEL_TOLERANCE:
        return None
    return best[1], best[2], best[3]


def _cut_along(source: np.ndarray, target: np.ndarray, radius: float, level: float, rng: np.random.Generator):
    """(miss, source kept, target kept, overlap reached) of the best pair of opposite half-spaces
    along one random direction (miss: how far the shares are from `level`); None where the clouds
    are too small to cut."""
    if len(source) < 2000 or len(target) < 2000:
        return None
    # Each source point's partners, and the target's: their highest / lowest coordinate along the direction decides whether one is kept.
    _, s_partners = cKDTree(target).query(source, k=8, distance_upper_bound=radius)
    _, t_partners = cKDTree(source).query(target, k=8, distance_upper_bound=radius)
    best = None
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    along_s, along_t = source @ d, target @ d
    top = np.append(along_t, -np.inf)[s_partners].max(axis=1)  # a source point keeps a partner where this is above the target's plane
    bottom = np.append(along_s, np.inf)[t_partners].min(axis=1)
    for a in np.quantile(along_s, np.linspace(0.15, 1.0, 18)):
        kept_s = along_s <= a
        for b in np.quantile(along_t, np.linspace(0.0, 0.85, 18)):
            kept_t = along_t >= b
            if kept_s.sum() < 2000 or kept_t.sum() < 2000:
                continue
            shares = (float(np.mean(top[kept_s] >= b)), float(np.mean(bottom[kept_t] <= a)))
            miss = max(abs(shares[0] - level), abs(shares[1] - level))
            if best is None or miss < best[0]:
                best = (miss, source[kept_s], target[kept_t], min(shares))
    return best


def _turned(source: np.ndarray, size: float, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """The (N, 3) source turned by a uniform 0-180 degrees about a random axis through its
    centroid and moved by about 0.3 x `size`; and T_target_source (4, 4) that takes it back."""
    from o3dsoft.transforms import apply_transform, axis_angle_to_matrix, rigid

    axis = rng.normal(size=3)
    R = axis_angle_to_matrix(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(0.0, 180.0)))
    centre = source.mean(axis=0)
    move = rigid(R, centre - R @ centre + rng.normal(size=3) * 0.3 * size)
    return apply_transform(move, source), np.linalg.inv(move)


def run(data: Path, levels, repeats: int, seed: int) -> List[dict]:
    """One record per pair made: its base, kind, level and overlap reached, and per method
    ("o3dsoft", "fpfh-ransac+icp") right, flagged (o3dsoft) and time (ms)."""
    from o3dsoft.bench import BenchConfig, BenchPair, run_pair
    from o3dsoft.coarse import load_model
    from o3dsoft.preprocess import scene_size

    rng = np.random.default_rng(seed)
    config, model = BenchConfig(methods=("o3dsoft", "fpfh-ransac+icp")), load_model()
    threshold = config.register.confidence.likely_failed_below
    records = []
    for name, kind, source, target in bases(data, rng):
        for level in [level for level in levels for _ in range(repeats)]:
            made = cut(source, target, level, rng)
            if made is None:
                print(f"{name}: no cut reaches {level:.0%}", flush=True)
                continue
            kept_s, kept_t, reached = made
            size = scene_size(kept_t)
            moved, truth = _turned(kept_s, size, rng)
            pair = BenchPair("partial", len(records), moved, kept_t, truth, name, origin=moved.mean(axis=0))
            outcome = run_pair(pair, config, model)
            record: Dict = {"base": name, "kind": kind, "level": level, "overlap": reached, "points": [len(moved), len(kept_t)], "error": outcome.error}
            for row, errors in outcome.scored:
                right = errors.rotation_deg <= RIGHT_DEG and errors.translation <= RIGHT_SHARE * size
                flagged = row["confidence"] != "" and row["confidence"] < threshold
                record[row["method"]] = {"right": bool(right), "flagged": bool(flagged), "rotation_deg": errors.rotation_deg, "ms": row["time_total_ms"]}
            records.append(record)
            ours = record.get("o3dsoft", {})
            print(f"{name} at {reached:.0%}: o3dsoft {'right' if ours.get('right') else 'wrong'}{', flagged' if ours.get('flagged') else ''}", flush=True)
    return records


def table(records: List[dict], levels) -> str:
    """Per kind and level: pairs; o3dsoft's right share, wrong results trusted, right results
    flagged and median time; FPFH + RANSAC + ICP's right share and median time."""
    lines = [
        "overlap | pairs | o3dsoft right | wrong trusted | right flagged | ms | FPFH + RANSAC + ICP right | ms",
        "(right: higher is better; wrong trusted, right flagged, ms (median per pair): lower is better)",
    ]
    for kind in ("pair", "halves"):
        lines.append(f"-- {'two scans' if kind == 'pair' else 'one scan, two random halves'}")
        for level in levels:
            chosen = [r for r in records if r["kind"] == kind and r["level"] == level and "o3dsoft" in r]
            if not chosen:
                continue
            ours = [r["o3dsoft"] for r in chosen]
            theirs = [r["fpfh-ransac+icp"] for r in chosen if "fpfh-ransac+icp" in r]
            right = sum(o["right"] for o in ours)
            lines.append(
                f"{level:.0%} | {len(chosen)} | {100 * right / len(ours):.0f} % | {sum(not o['right'] and not o['flagged'] for o in ours)} of {len(ours) - right}"
                f" | {sum(o['right'] and o['flagged'] for o in ours)} of {right} | {np.median([o['ms'] for o in ours]):.0f}"
                f" | {100 * np.mean([t['right'] for t in theirs]):.0f} % | {np.median([t['ms'] for t in theirs]):.0f}"
            )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"), help="the folder of real_scans/ and stanford_bunny/")
    parser.add_argument("--levels", type=float, nargs="+", default=list(LEVELS), help="overlap shares to cut the pairs to")
    parser.add_argument("--repeats", type=int, default=2, help="pairs cut per base pair and level")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="write every pair's record here (JSON)")
    args = parser.parse_args(argv)
    records = run(args.data, args.levels, args.repeats, args.seed)
    if args.out:
        args.out.write_text(json.dumps({"levels": args.levels, "repeats": args.repeats, "seed": args.seed, "pairs": records}, indent=1))
    print(table(records, args.levels))


if __name__ == "__main__":
    main()
