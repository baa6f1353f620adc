"""Ship a trained model as the package default: copy it into weights/ with a card that holds its
training record and its accuracy measured here, on ModelNet40 test pairs.

    python -m benchmarks.ship_model RUN_DIR [--name default] [--limit 300] [--protocol paper dcp wide45] [--iterations 1 2]
        [--search auto] [--note TEXT]

RUN_DIR is an `o3dsoft train` output folder (checkpoint.pt, and model_card.json once the run
finished; a run stopped earlier is described from its checkpoint). The model is exported again
from the checkpoint with the current code. Writes weights/o3dsoft_NAME.pt and
weights/o3dsoft_NAME.json (NAME "default": the model o3dsoft uses unless told otherwise; others
are loaded by name, e.g. ``--weights paper``).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import tempfile
from pathlib import Path

import torch

from benchmarks.eval_model import DEFAULT_DATA, evaluate_protocol
from o3dsoft.coarse import load_model, sha256_of
from o3dsoft.train import checkpoint_card, export_checkpoint

WEIGHTS = Path(__file__).resolve().parents[1] / "weights"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--limit", type=int, default=300, help="first N test pairs per protocol (0: the whole split)")
    ap.add_argument("--iterations", type=int, nargs="+", default=[1], help="coarse-stage network passes to evaluate")
    ap.add_argument("--protocol", nargs="+", default=["paper", "dcp", "wide45"])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--search", choices=["auto", "always", "off"], default="auto", help="the global search during the evaluation")
    ap.add_argument("--note", default="")
    ap.add_argument("--name", default="default", help="shipped as weights/o3dsoft_NAME.pt")
    args = ap.parse_args()

    card_file = args.run_dir / "model_card.json"
    card = json.loads(card_file.read_text()) if card_file.is_file() else checkpoint_card(args.run_dir / "checkpoint.pt")
    target = WEIGHTS / f"o3dsoft_{args.name}.pt"
    # Re-exported from the checkpoint, so that the shipped file carries the current inference code;
    # measured outside weights/ (where a file must match its card) and copied there with its card.
    with tempfile.TemporaryDirectory() as tmp:
        staging = Path(tmp) / target.name
        export_checkpoint(args.run_dir / "checkpoint.pt", staging)
        model = load_model(staging)
        evaluation = []
        for p in args.protocol:
            for iterations in args.iterations:
                evaluation.append(evaluate_protocol(model, args.data, p, args.limit, seed=0, iterations=iterations, search=args.search))
                print(json.dumps(evaluation[-1]), flush=True)
        shutil.copyfile(staging, target)
    card.update(
        model_file=target.name,
        sha256=sha256_of(target),
        note=args.note,
        evaluation={
            "what": "o3dsoft.register with this model alone (no second network) on the first N ModelNet40 test pairs of each protocol "
            f"(seed 0; N = 0: all), with 1 or more coarse-stage network passes, global search {args.search}; "
            "errors: rotation in degrees, translation in shape units (shapes have radius 1), lower is better; "
            "recall: share of pairs, higher is better",
            "command": f"python -m benchmarks.ship_model {args.run_dir} --name {args.name} --limit {args.limit} --protocol {' '.join(args.protocol)} "
            f"--iterations {' '.join(map(str, args.iterations))} --search {args.search}",
            "machine": f"{platform.machine()}, {torch.get_num_threads()} torch threads, torch {torch.__version__}",
            "results": evaluation,
        },
    )
    target.with_suffix(".json").write_text(json.dumps(card, indent=2) + "\n")


if __name__ == "__main__":
    main()
