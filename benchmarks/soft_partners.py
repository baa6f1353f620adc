"""How sharp a network's soft assignment is at the true pose, on ModelNet40 test pairs.

    python -m benchmarks.soft_partners [--weights incongruent] [--protocol incongruent dcp] [--limit 20]
        [--data ../shared/data/modelnet40_ply_hdf5_1024] [--points-per-shape 1024]
        [--scans ../shared/data/stanford_bunny [--scan-points 1024]]

Per protocol, over the first N pairs (clouds normalised as in training, the network's own
forward pass), prints as JSON:

- ``max_w_times_m``: the mean over source points of max_j W_ij times the target's size M: 1 for
  uniform weights (every soft partner the target's centroid), M for one-hot rows;
- ``match_loss``: :func:`o3dsoft.model.match_loss` (nats, lower is better), with
  ``uniform_match_loss``, its value for uniform weights on the same pairs;
- ``positives_per_point``: target points within the loss's reach of each source point's true place;
- ``overlap_auc``: the ROC AUC of the weights w_i = max_j W_ij for telling the source points in
  the overlap (:func:`o3dsoft.model.overlap_labels`: a target point within 3 median target
  spacings of where the point truly lies) from the rest (median over the pairs that have both;
  higher is better, 0.5 is chance; None where no pair has both). Weighted Procrustes trusts each
  point by w_i, so on partial overlap a network with a high ``overlap_auc`` leaves out the points
  without a partner. The spacings, not the loss's fixed reach: on sparse samplings many points in
  the overlap have no target point within 0.06 (a fifth of them on ``incongruent``);
- ``head_overlap_auc``, ``head_target_overlap_auc``: the same for the overlap head's logits of the
  source's and the target's points (networks with ``NetConfig.overlap``; else None).

``--scans FOLDER`` reports the three AUCs on every pair of a folder of scans instead (as
``o3dsoft bench scans`` takes them), the network's samples prepared as ``register`` prepares them
(``--scan-points`` per cloud), the source turned by the true rotation: scans come at any
relative pose, far beyond the training protocols' turns.

A network whose soft partners are near-uniform (``max_w_times_m`` near 1) does not find
correspondences: its rotation comes from a small first-order term of W (docs/incongruent.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import List, Optional

import numpy as np
import torch

from benchmarks.eval_model import DEFAULT_DATA
from benchmarks.network_from_truth import eager_network, scan_samples
from o3dsoft.bench import roc_auc
from o3dsoft.data import get_protocol, load_pairs
from o3dsoft.model import SoftAlignNet, match_loss, overlap_labels, true_partners, true_places
from o3dsoft.train import normalised_batch


def sharpness(model: SoftAlignNet, data: str, protocol: str, limit: int, seed: int = 0, reach: float = 0.06, points_per_shape: int = 1024) -> dict:
    """The figures above for the first `limit` test pairs of `protocol` (one batch: equal point counts)."""
    pairs = load_pairs(data, "test", get_protocol(protocol), seed, points_per_shape)
    src, tgt, R, t = normalised_batch([pairs[i] for i in range(min(limit, len(pairs)))])
    model.eval()
    with torch.no_grad():
        model(src, tgt)
        W = model.soft_partners
        near = true_partners(true_places(src, R, t), tgt, reach).to(W.dtype)
        has = near.amax(dim=-1)
        in_s, in_t = overlap_labels(src, tgt, R, t)
        head = model.overlap_logits if len(model.overlap) else None  # set by the forward pass above
        uniform = -(torch.log(near.sum(-1).clamp(min=1) / W.shape[-1]) * has).sum() / has.sum().clamp(min=1)
        return {
            "protocol": protocol,
            "pairs": int(src.shape[0]),
            "max_w_times_m": float(W.amax(-1).mean() * W.shape[-1]),
            "match_loss": float(match_loss(src, tgt, W, R, t, reach)),
            "uniform_match_loss": float(uniform),
            "positives_per_point": float(near.sum(-1).mean()),
            "temperature": float(torch.exp(model.log_tau)),
            "overlap_auc": partner_auc(W.amax(-1), in_s),
            "head_overlap_auc": None if head is None else partner_auc(head[0], in_s),
            "head_target_overlap_auc": None if head is None else partner_auc(head[1], in_t),
        }


def scan_overlap_auc(model: SoftAlignNet, folder: Path, points: int = 1024) -> dict:
    """``overlap_auc``, ``head_overlap_auc`` and ``head_target_overlap_auc`` (medians over the
    pairs) on every pair of the scans in `folder`, `points` per cloud, the source turned by the
    true rotation."""
    model.eval()
    w, head_s, head_t, in_s, in_t = [], [], [], [], []
    with torch.no_grad():
        for source, target, T in scan_samples(folder, model.k, points):
            # The source turned by the true rotation (the network centres it itself); the labels
            # then need only the true translation.
            src, tgt = (torch.as_tensor(c, dtype=torch.float32)[None] for c in (source @ T[:3, :3].T, target))
            R, t = torch.eye(3)[None], torch.as_tensor(T[None, :3, 3], dtype=torch.float32)
            model(src, tgt)
            labels = overlap_labels(src, tgt, R, t)
            w.append(model.soft_partners.amax(-1)[0])
            in_s.append(labels[0][0])
            in_t.append(labels[1][0])
            if len(model.overlap):
                head_s.append(model.overlap_logits[0][0])
                head_t.append(model.overlap_logits[1][0])
    return {
        "scans": str(folder),
        "pairs": len(w),
        "points": points,
        "overlap_auc": _median_auc(w, in_s),
        "head_overlap_auc": _median_auc(head_s, in_s) if head_s else None,
        "head_target_overlap_auc": _median_auc(head_t, in_t) if head_t else None,
    }


def _median_auc(scores: List[torch.Tensor], labels: List[torch.Tensor]) -> Optional[float]:
    """Median over pairs of the ROC AUC of each pair's scores (N,) for its labels (N,) bool."""
    aucs = [roc_auc(s.double().numpy(), y.numpy()) for s, y in zip(scores, labels)]
    aucs = [a for a in aucs if a is not None]
    return float(np.median(aucs)) if aucs else None


def partner_auc(w: torch.Tensor, has_partner: torch.Tensor) -> Optional[float]:
    """Median over pairs of the ROC AUC of the scores w (B, N) for has_partner (B, N) bool (ties
    count half); None where no pair has points of both kinds."""
    return _median_auc(list(w.cpu()), list(has_partner.cpu()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="incongruent", help="a shipped model's name, an exported model file or a training checkpoint")
    ap.add_argument("--protocol", nargs="+", default=["incongruent", "dcp"])
    ap.add_argument("--limit", type=int, default=20)
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--points-per-shape", type=int, default=1024, help="points of each shape of --data to use")
    ap.add_argument("--scans", type=Path, help="the AUCs on every pair of this folder of scans instead")
    ap.add_argument("--scan-points", type=int, default=1024, help="with --scans: points per cloud for the network")
    args = ap.parse_args()
    model = eager_network(args.weights)
    if args.scans is not None:
        print(json.dumps(scan_overlap_auc(model, args.scans, args.scan_points)), flush=True)
        return
    for p in args.protocol:
        print(json.dumps(sharpness(model, args.data, p, args.limit, points_per_shape=args.points_per_shape)), flush=True)


if __name__ == "__main__":
    main()
