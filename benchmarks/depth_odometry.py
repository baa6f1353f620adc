"""Odometry on depth frames: ``o3dsoft.odometry`` on the views of ``benchmarks.indoor_rooms``
taken as a sequence around its loop.

    python -m benchmarks.depth_odometry [--loop 72] [--frames 30] [--pixels 200] [--seeds 0 1]
        [--out FILE.json]

`--loop` views make the whole loop (72: 5 degrees and 0.17 m between frames; 12: 30 degrees and
1 m), the first `--frames` of them are registered. A frame is a depth camera's view of `--pixels`
across (4 mm range noise), in metres in its own frame. A step (a frame's pose relative to the
previous one's) is wrong beyond 1 degree or 2 cm. Run it alone on the machine: the times are
medians of its own run.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import List

import numpy as np

from benchmarks.indoor_rooms import scene, views


def measure(clouds: List[np.ndarray], truth: List[np.ndarray], model) -> dict:
    """One odometry run: the last frame's drift, its step errors, wrong / trusted-wrong / flagged
    steps, the time per frame and the points of the last step's clouds at each stage."""
    import o3dsoft
    from o3dsoft.odometry import errors_against

    result = o3dsoft.odometry(clouds, model=model)
    rotation, translation, drift, _ = errors_against(result, truth)
    wrong, flagged = (rotation > 1.0) | (translation > 0.02), np.array(result.flagged[1:])
    steps = [s for s in result.steps if s is not None]
    return {
        "frames": len(clouds),
        "points_per_frame": int(np.median([len(c) for c in clouds])),
        "drift_m": drift.translation,
        "drift_deg": drift.rotation_deg,
        "step_translation_m_median": float(np.median(translation)),
        "wrong": int(wrong.sum()),
        "trusted_wrong": int((wrong & ~flagged).sum()),
        "flagged": int(flagged.sum()),
        "ms_per_frame": float(np.median([s.timings_ms["total"] for s in steps])),
        "stage_ms": {k: float(np.median([s.timings_ms.get(k, 0.0) for s in steps])) for k in sorted({k for s in steps for k in s.timings_ms})},
        "last_points_used": {k: list(v) for k, v in steps[-1].points_used.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loop", type=int, default=72, help="views around the whole loop")
    ap.add_argument("--frames", type=int, default=30, help="the first this many are registered")
    ap.add_argument("--pixels", type=int, default=200)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if not 2 <= args.frames <= args.loop or args.pixels < 8:
        ap.error("--frames must be from 2 to --loop, --pixels at least 8")
    import o3dsoft

    model = o3dsoft.load_model()
    rays = scene()
    rows = []
    print("seed  frames  points  drift (mm / deg)  step median (mm)  wrong  trusted wrong  flagged  ms per frame   (all lower is better)")
    for seed in args.seeds:
        clouds, truth = views(args.loop, args.pixels, seed, rays=rays)
        row = {"seed": seed, **measure(clouds[: args.frames], truth[: args.frames], model)}
        rows.append(row)
        print(
            f"{seed:4d} {row['frames']:7d} {row['points_per_frame']:7d}  {1000 * row['drift_m']:8.1f} / {row['drift_deg']:5.2f}"
            f"  {1000 * row['step_translation_m_median']:14.2f}  {row['wrong']:5d}  {row['trusted_wrong']:13d}  {row['flagged']:7d}"
            f"  {row['ms_per_frame']:11.0f}",
            flush=True,
        )
    if args.out:
        args.out.write_text(json.dumps({"command": vars(args) | {"out": str(args.out)}, "runs": rows, "time": time.strftime("%Y-%m-%d %H:%M")}, indent=1))


if __name__ == "__main__":
    main()
