"""Write the README's "Results" section from bench run folders (never typed by hand).

    python -m benchmarks.results_table RUN [RUN ...] [--readme README.md] [--marker results] [--short]
    python -m benchmarks.results_table --scans SCANS_RUN          # the real-scans table (marker: scans)

Each RUN is a bench run folder or a copy of its summary.json; the README's table is made from
the copies in benchmarks/results/ (``python -m benchmarks.results_table benchmarks/results/*.json``),
so that it can be made again from the repository alone, from runs of different sessions.

Replaces the text between the markers ``<!-- MARKER:start -->`` and ``<!-- MARKER:end -->``
(MARKER: ``results`` unless told) with each run's command, machine and versions, a short table
of o3dsoft against FPFH + RANSAC + ICP, and (unless --short) one table per protocol (from
summary.json). Several
runs (e.g. the protocols of the whole split run in parts, each within a session) give one table,
protocols in the order of :data:`o3dsoft.data.PROTOCOLS`; each protocol must come from one run,
so that its time ratio compares methods measured in the same run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import List, Sequence, Union

from o3dsoft.bench import recall_keys
from o3dsoft.data import PROTOCOLS
from o3dsoft.errors import counted


def thresholds(doc: dict, protocol: str) -> List[dict]:
    """The recall thresholds of `protocol` in a summary document: one list for every protocol,
    or (runs with real scans of several kinds) one per protocol."""
    recall = doc["recall_thresholds"]
    return recall[protocol] if isinstance(recall, dict) else recall


def compared(doc: dict, ours: str, theirs: str) -> list:
    """Lines of a short table, one row per protocol (all categories): recall at the first and the
    last threshold and median time of `ours` and `theirs`, the time ratio, ours' confidence AUC
    and false alarms (right results flagged), and how many of ours' failures fit the clouds as well as the truth (runs with the oracle).
    Empty when the run lacks either method."""
    rows = {(s["protocol"], s["method"]): s for s in doc["summaries"] if s["subset"] == "all"}
    protocols = list(dict.fromkeys(p for p, _ in rows))
    if not all((p, m) in rows for p in protocols for m in (ours, theirs)):
        return []
    name = doc["methods"]
    r1, r5 = thresholds(doc, protocols[0])[0], thresholds(doc, protocols[0])[-1]
    lines = [
        "",
        f"{name[ours]} against {name[theirs]}, measured in the same run: recall within "
        f"({r1['rotation_deg']:g} deg, {r1['translation']:g}) / ({r5['rotation_deg']:g} deg, {r5['translation']:g}) "
        "(higher is better), median time per pair (lower is better); false alarms: right results (at the last "
        "threshold) flagged likely failed (lower is better). Failures that fit as the truth does: "
        "failures whose pose fits the two clouds as well as ICP from the ground truth (input Chamfer distance "
        "at most 1.1 times the oracle's), which the clouds cannot tell from the truth (mostly symmetric copies; "
        "on cropped clouds the count says less) "
        "(- : a run without the oracle or before this count):",
        "",
        f"| protocol | {name[ours]} recall | {name[theirs]} recall | {name[ours]} time (ms) | {name[theirs]} time (ms) | "
        f"time ratio | {name[ours]} confidence ROC AUC, false alarms | {name[ours]} failures that fit as the truth does |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def recall(s: dict) -> str:
        keys = recall_keys(s)
        return f"{100 * s[keys[0]]:.1f} / {100 * s[keys[-1]]:.1f} %"

    for p in protocols:
        a, b = rows[p, ours], rows[p, theirs]
        auc, alarms = a.get("confidence_auc"), a.get("false_alarm_share")
        trust = f"{'-' if auc is None else f'{auc:.3f}'}, {'-' if alarms is None else f'{100 * alarms:.0f} %'}"
        copies = f"{a['failures_as_truth']} of {a['failures']}" if "failures" in a else "-"
        lines.append(
            f"| `{p}` | {recall(a)} | {recall(b)} | {a['time_ms_median']:.0f} | {b['time_ms_median']:.0f} | "
            f"{a['time_ms_median'] / b['time_ms_median']:.2f} | {trust} | {copies} |"
        )
    return lines


def run_lines(doc: dict) -> List[str]:
    """A run's command, size, duration, machine, versions and weights."""
    desc, v = doc["description"], doc["versions"]
    limit = desc.get("limit")
    commit = ""
    if "commit" in v:  # runs from a git checkout: the short hash, marked when files had changed
        commit = f" (commit {v['commit'][:7]}{'+changes' if v['commit'].endswith('+changes') else ''})"
    return [
        f"Command: `{desc.get('command', 'o3dsoft bench modelnet40')}`"
        + (f" (first {limit} test pairs per protocol)" if limit else " (the whole ModelNet40 test split)")
        + f"; {_size(doc)}.",
        f"Machine: {v['machine']}; o3dsoft {v['o3dsoft']}{commit}, torch {v['torch']}, Open3D {v['open3d']}. "
        f"Weights sha256 `{((doc.get('weights') or {}).get('sha256') or '-')[:12]}`.",
    ]


def _size(doc: dict) -> str:
    """ "208 pairs in 8.9 min", with what cut the run short or left pairs and methods out."""
    n, failed = doc["pairs_completed"], len(doc.get("pairs_failed") or [])
    text = f"{counted(n, 'pair')} in {doc['seconds'] / 60:.1f} min" + (" (interrupted)" if doc["interrupted"] else "")
    if failed:
        text += f"; {failed} pair{' was' if failed == 1 else 's were'} left out: no method could run on {'it' if failed == 1 else 'them'}"
    raised = sorted({f"{doc['methods'].get(s['method'], s['method'])}" for s in doc["summaries"] if s.get("raised")})
    if raised:
        text += f"; raised an error on some pairs, scored there as the pose as given: {', '.join(raised)}"
    return text


def merged(docs: Sequence[dict]) -> dict:
    """The runs' summaries as one document (every run's methods, each protocol's thresholds),
    protocols in the order of PROTOCOLS. Raises SystemExit when two runs hold one protocol."""
    seen = set()
    for doc in docs:
        for p in {s["protocol"] for s in doc["summaries"]}:
            if p in seen:
                raise SystemExit(f"protocol {p} is in two of the runs; give each protocol from one run")
            seen.add(p)
    order = {name: i for i, name in enumerate(PROTOCOLS)}
    summaries = [s for doc in docs for s in doc["summaries"]]
    summaries.sort(key=lambda s: order.get(s["protocol"], len(order)))  # stable: methods keep their order
    recall = {s["protocol"]: thresholds(doc, s["protocol"]) for doc in docs for s in doc["summaries"]}
    methods = {name: title for doc in docs for name, title in doc["methods"].items()}
    return {"methods": methods, "recall_thresholds": recall, "summaries": summaries}


def summary_of(run: Path) -> dict:
    """A run's summary: from a run folder (its summary.json) or from a summary file itself, such
    as the copies kept in benchmarks/results/ (run folders are not kept in the repository)."""
    path = run if run.is_file() else run / "summary.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise SystemExit(f"{run}: no such file, nor a folder with a summary.json; expected a bench run folder or its summary.json") from None
    except (UnicodeDecodeError, ValueError) as e:
        raise SystemExit(f"{path}: not a JSON file ({e}); expected a bench run's summary.json") from None
    if not isinstance(doc, dict) or not all(key in doc for key in ("summaries", "methods", "description", "versions")):
        raise SystemExit(f"{path}: not a bench run's summary.json (no summaries, methods, description or versions)")
    return doc


def is_scans(doc: dict) -> bool:
    """Whether a summary is of a ``bench scans`` run (its description lists the folders)."""
    return "folders" in doc["description"]


def markdown(runs: Union[Path, Sequence[Path]], short: bool = False) -> str:
    runs = [runs] if isinstance(runs, Path) else list(runs)
    docs = [summary_of(run) for run in runs]
    for run, d in zip(runs, docs):
        if is_scans(d):
            raise SystemExit(f"{run}: a bench scans run; its table is made with --scans")
    doc = merged(docs)
    recall = thresholds(doc, doc["summaries"][0]["protocol"])
    r1, r5 = recall[0], recall[-1]
    lines: List[str] = []
    for d in docs:
        lines += run_lines(d)
    lines += [
        "",
        "Rotation errors in degrees, translation in shape units (radius-1 shapes): lower is better. "
        f"Recall: share of pairs with rotation error < {r1['rotation_deg']:g} deg and translation error < {r1['translation']:g} "
        f"(and < {r5['rotation_deg']:g} deg, < {r5['translation']:g}): higher is better. Time: per pair, lower is better.",
    ]
    lines += compared(doc, "o3dsoft", "fpfh-ransac+icp")
    if short:
        return "\n".join(lines)
    block = None
    for s in doc["summaries"]:
        if (s["protocol"], s["subset"]) != block:
            block = (s["protocol"], s["subset"])
            title = f"**{s['protocol']}**" + (" without symmetric categories" if s["subset"] != "all" else "")
            lines += [
                "",
                title,
                "",
                "| method | pairs | rotation mean / median (deg) | translation mean | Euler RMSE (deg) | "
                f"recall {r1['rotation_deg']:g} deg | recall {r5['rotation_deg']:g} deg | time median / p90 (ms) |",
                "|---|---|---|---|---|---|---|---|",
            ]
        rk = recall_keys(s)
        lines.append(
            f"| {doc['methods'][s['method']]} | {int(s['pairs'])} | {s['rotation_deg_mean']:.3g} / {s['rotation_deg_median']:.3g} | "
            f"{s['translation_mean']:.3g} | {s['euler_rmse_deg']:.3g} | {100 * s[rk[0]]:.1f} % | {100 * s[rk[-1]]:.1f} % | "
            f"{s['time_ms_median']:.0f} / {s['time_ms_p90']:.0f} |"
        )
    return "\n".join(lines)


def scans_markdown(run: Path) -> str:
    """The README's real-scans table from one ``bench scans`` run: per folder (its kind and
    thresholds), each method's recall at both thresholds and median time, and o3dsoft's
    confidence ROC AUC and false alarms; a run with ``--turns`` gives each folder's turned pairs
    (protocol "FOLDER turned") in the same row."""
    doc = summary_of(run)
    if not is_scans(doc):
        raise SystemExit(f"{run}: not a bench scans run; a ModelNet40 run's table is made without --scans")
    desc, names = doc["description"], doc["methods"]
    lines = run_lines(doc)[1:]
    lines[0:0] = [f"Command: `{desc.get('command', 'o3dsoft bench scans')}`; {_size(doc)}."]
    folders = {f["folder"]: f for f in desc.get("folders", [])}
    rows = {(s["protocol"], s["method"]): s for s in doc["summaries"] if s["subset"] == "all"}
    turns = max((f.get("turns", 0) for f in folders.values()), default=0)
    columns = ["recall"] + (["time (ms)", f"turned {turns} times: recall", "time (ms)"] if turns else ["time (ms)"])
    lines += [
        "",
        "Recall: share of pairs within each kind's tight / loose test (higher is better); time: median per pair, "
        "measured in the same run (lower is better); false alarms: right results flagged (lower is better)"
        + ("; turned: each pair again with the source turned about its centroid by random rotations (`--turns`)." if turns else "."),
        "",
        f"| scans | test (tight / loose) | method | {' | '.join(columns)} | confidence ROC AUC, false alarms{' (turned)' if turns else ''} |",
        "|---|---|---|" + "---|" * len(columns) + "---|",
    ]

    def cells(s: dict) -> List[str]:
        keys = recall_keys(s)
        return [f"{100 * s[keys[0]]:.0f} / {100 * s[keys[-1]]:.0f} %", f"{s['time_ms_median']:.0f}"]

    def trust(s: dict) -> str:
        if "confidence_auc" not in s:
            return ""
        auc = "-" if s["confidence_auc"] is None else f"{s['confidence_auc']:.2f}"
        alarms = "-" if s.get("false_alarm_share") is None else f"{100 * s['false_alarm_share']:.0f} %"
        return f"{auc}, {alarms}"

    for (protocol, method), s in rows.items():
        if protocol.endswith(" turned") and protocol[: -len(" turned")] in folders:
            continue  # in its folder's row
        tight, loose = thresholds(doc, protocol)[0], thresholds(doc, protocol)[-1]
        unit = folders.get(protocol, {}).get("unit", "m")  # runs that did not record it used bench scans' default
        test = f"{tight['rotation_deg']:g} deg / {tight['translation']:.3g} {unit}, {loose['rotation_deg']:g} deg / {loose['translation']:.3g} {unit}"
        turned = rows.get((f"{protocol} turned", method))
        values = cells(s) + (cells(turned) if turned else ["", ""] if turns else [])
        kind = folders.get(protocol, {}).get("kind", "")
        lines.append(f"| {protocol} ({kind}, {counted(int(s['pairs']), 'pair')}) | {test} | {names[method]} | {' | '.join(values)} | {trust(turned or s)} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+", help="bench run folders or summary.json files (each protocol from one of them)")
    ap.add_argument(
        "--readme",
        type=Path,
        default=Path(__file__).resolve().parents[1] / "README.md",
        help="the file whose marked section is replaced, in place (default: the repository's README.md)",
    )
    ap.add_argument("--print", action="store_true", help="print the section instead of writing it")
    ap.add_argument("--marker", default="results", help="the README section's marker name")
    ap.add_argument("--short", action="store_true", help="only the runs and the short table, not one table per protocol")
    ap.add_argument("--scans", action="store_true", help="one `bench scans` run: the real-scans table (marker `scans` unless told)")
    args = ap.parse_args()
    if args.scans and len(args.runs) > 1:
        raise SystemExit(f"--scans takes one bench scans run, got {len(args.runs)}")
    marker = "scans" if args.scans and args.marker == "results" else args.marker
    START, END = f"<!-- {marker}:start -->", f"<!-- {marker}:end -->"
    text = args.readme.read_text()
    if START not in text or END not in text:
        raise SystemExit(f"{args.readme}: no {START} ... {END} markers")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    table = scans_markdown(args.runs[0]) if args.scans else markdown(args.runs, args.short)
    if args.print:
        print(table)
        return
    args.readme.write_text(head + START + "\n" + table + "\n" + END + tail)
    print(f"updated {args.readme} from {', '.join(map(str, args.runs))}")


if __name__ == "__main__":
    main()
