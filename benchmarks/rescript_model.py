"""Script the shipped models again with the current inference code: same weights, same card.

    python -m benchmarks.rescript_model [NAME ...]     (default: every shipped model)

A TorchScript file carries the code of the release that exported it, so speed-ups of the
network's inference reach the shipped models only this way. Each re-scripted file must give
the old file's outputs on ModelNet40 test pairs, to float32 rounding (:data:`TOLERANCE`: the
inference path folds each BatchNorm into its linear map, which rounds differently), before it
replaces it; its card gets the new sha256 and a line in its note.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path

import torch

from benchmarks.eval_model import DEFAULT_DATA
from o3dsoft.coarse import bundled_model_names, bundled_weights_path, load_model, rescript, sha256_of
from o3dsoft.data import get_protocol, load_pairs
from o3dsoft.io import atomic_output

CHECK_PAIRS = 20
RESCRIPTED = re.compile(r"\s*Re-scripted with later inference code \(benchmarks/rescript_model\.py\); same weights, .*?(?:file's|identical)\.")
TOLERANCE = 1e-4  # largest difference allowed in any entry of R, t (normalised units) and w


def largest_difference(old, new, data: str) -> float:
    """The largest difference between both models' (R, t, w) on the first dcp test pairs, one
    at a time and as a batch."""
    pairs = load_pairs(data, "test", get_protocol("dcp"), 0)
    clouds = [(pairs[i].source, pairs[i].target) for i in range(CHECK_PAIRS)]
    src = torch.stack([torch.as_tensor(s - s.mean(0), dtype=torch.float32) for s, _ in clouds])
    tgt = torch.stack([torch.as_tensor(t - t.mean(0), dtype=torch.float32) for _, t in clouds])
    worst = 0.0
    for batch in ((src[:1], tgt[:1]), (src, tgt)):
        for a, b in zip(old.run(*batch), new.run(*batch)):
            worst = max(worst, float((a - b).abs().max()))
    return worst


def rescripted_note(note: str, worst: float) -> str:
    """A card's note with one sentence saying it was re-scripted, the latest (earlier re-scripts'
    sentences are dropped), and how far the new file's outputs lie from the old one's."""
    outputs = "identical to the previous file's" if worst == 0 else f"within {worst:.1g} of the previous file's"
    return (
        RESCRIPTED.sub("", note).strip() + f" Re-scripted with later inference code (benchmarks/rescript_model.py); same weights, outputs {outputs}."
    ).strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="shipped models (default: all)")
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    args = ap.parse_args()
    for name in args.names or bundled_model_names():
        path = bundled_weights_path(name)
        old = load_model(path)
        with tempfile.TemporaryDirectory() as tmp:
            new = load_model(rescript(old, Path(tmp) / path.name))
            worst = largest_difference(old, new, args.data)
            if worst > TOLERANCE:
                raise SystemExit(f"{name}: the re-scripted model's outputs differ by up to {worst:.2g}; {path} left as it was")
            with atomic_output(path) as out:
                out.write_bytes(Path(new.path).read_bytes())
        card_path = path.with_suffix(".json")
        card = json.loads(card_path.read_text())
        card["sha256"] = sha256_of(path)
        card["note"] = rescripted_note(card.get("note", ""), worst)
        card_path.write_text(json.dumps(card, indent=2) + "\n")
        print(f"{name}: {path} re-scripted, sha256 {card['sha256'][:12]}, outputs within {worst:.2g}")


if __name__ == "__main__":
    main()
