"""Write the README's "Results" section from a bench run folder (never typed by hand).

    python -m benchmarks.results_table RUN_DIR [--readme README.md] [--marker results]

Replaces the text between the markers ``<!-- MARKER:start -->`` and ``<!-- MARKER:end -->``
(MARKER: ``results`` unless told) with the run's command, machine, versions, a short table of
o3dsoft against FPFH + RANSAC + ICP, and one table per protocol (from summary.json).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from o3dsoft.bench import recall_keys


def compared(doc: dict, ours: str, theirs: str) -> list:
    """Lines of a short table, one row per protocol (all categories): recall at the first
    threshold and median time of `ours` and `theirs`, the time ratio, and ours' confidence AUC.
    Empty when the run lacks either method."""
    rows = {(s["protocol"], s["method"]): s for s in doc["summaries"] if s["subset"] == "all"}
    protocols = list(dict.fromkeys(p for p, _ in rows))
    if not all((p, m) in rows for p in protocols for m in (ours, theirs)):
        return []
    name = doc["methods"]
    r1 = doc["recall_thresholds"][0]
    lines = ["", f"In short, {name[ours]} against {name[theirs]} in the same run (recall at "
             f"{r1['rotation_deg']:g} deg / {r1['translation']:g}, higher is better; median time per pair, lower is better):", "",
             f"| protocol | {name[ours]} recall | {name[theirs]} recall | {name[ours]} time (ms) | {name[theirs]} time (ms) | "
             f"time ratio | {name[ours]} confidence ROC AUC |",
             "|---|---|---|---|---|---|---|"]
    for p in protocols:
        a, b = rows[p, ours], rows[p, theirs]
        key = recall_keys(a)[0]
        auc = a.get("confidence_auc")
        lines.append(f"| `{p}` | {100 * a[key]:.1f} % | {100 * b[key]:.1f} % | {a['time_ms_median']:.0f} | {b['time_ms_median']:.0f} | "
                     f"{a['time_ms_median'] / b['time_ms_median']:.2f} | {'-' if auc is None else f'{auc:.3f}'} |")
    return lines


def markdown(run: Path) -> str:
    doc = json.loads((run / "summary.json").read_text())
    desc, v = doc["description"], doc["versions"]
    recall = doc["recall_thresholds"]
    r1, r5 = recall[0], recall[-1]
    limit = desc.get("limit")
    lines = [
        f"Command: `{desc.get('command', 'o3dsoft bench modelnet40')}`"
        + (f" (first {limit} test pairs per protocol)" if limit else " (the whole ModelNet40 test split)")
        + f"; {doc['pairs_completed']} pairs in {doc['seconds'] / 60:.1f} min"
        + (" (interrupted)" if doc["interrupted"] else "") + ".",
        f"Machine: {v['machine']}; o3dsoft {v['o3dsoft']}, torch {v['torch']}, Open3D {v['open3d']}. "
        f"Weights sha256 `{(doc['weights']['sha256'] or '-')[:12]}`.",
        "",
        "Rotation errors in degrees, translation in shape units (radius-1 shapes): lower is better. "
        f"Recall: share of pairs with rotation error < {r1['rotation_deg']:g} deg and translation error < {r1['translation']:g} "
        f"(and < {r5['rotation_deg']:g} deg, < {r5['translation']:g}): higher is better. Time: per pair, lower is better.",
    ]
    lines += compared(doc, "o3dsoft", "fpfh-ransac+icp")
    block = None
    for s in doc["summaries"]:
        if (s["protocol"], s["subset"]) != block:
            block = (s["protocol"], s["subset"])
            title = f"**{s['protocol']}**" + (" without symmetric categories" if s["subset"] != "all" else "")
            lines += ["", title, "",
                      "| method | pairs | rotation mean / median (deg) | translation mean | Euler RMSE (deg) | "
                      f"recall {r1['rotation_deg']:g} deg | recall {r5['rotation_deg']:g} deg | time median / p90 (ms) |",
                      "|---|---|---|---|---|---|---|---|"]
        rk = recall_keys(s)
        lines.append(
            f"| {doc['methods'][s['method']]} | {int(s['pairs'])} | {s['rotation_deg_mean']:.3g} / {s['rotation_deg_median']:.3g} | "
            f"{s['translation_mean']:.3g} | {s['euler_rmse_deg']:.3g} | {100 * s[rk[0]]:.1f} % | {100 * s[rk[-1]]:.1f} % | "
            f"{s['time_ms_median']:.0f} / {s['time_ms_p90']:.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--readme", type=Path, default=Path(__file__).resolve().parents[1] / "README.md")
    ap.add_argument("--marker", default="results", help="the README section's marker name")
    args = ap.parse_args()
    START, END = f"<!-- {args.marker}:start -->", f"<!-- {args.marker}:end -->"
    text = args.readme.read_text()
    if START not in text or END not in text:
        raise SystemExit(f"{args.readme}: no {START} ... {END} markers")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    args.readme.write_text(head + START + "\n" + markdown(args.run) + "\n" + END + tail)
    print(f"updated {args.readme} from {args.run}")


if __name__ == "__main__":
    main()
