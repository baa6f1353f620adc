"""The network on scan pairs started near the truth: does it hold a right pose, or leave it?

    python -m benchmarks.network_from_truth [--weights default incongruent partial]
        [--scans ../shared/data/stanford_bunny] [--angles 0 15 30 45 90] [--passes 3] [--seed 0]
        [--overlap-only | --trim KEEP] [--modelnet PROTOCOL [--limit 50] [--data ../shared/data/modelnet40_ply_hdf5_1024]]

For every pair of a folder of scans (`o3dsoft.bench.scan_folder`, as `o3dsoft bench scans` takes
them), the network's samples of the two clouds are prepared as `register` prepares them
(`o3dsoft.pair.PreparedPair`); the source is turned onto the target by the ground-truth rotation
and then by a further random turn of each angle (degrees, about a random axis), and the network
runs `--passes` times from there, each pass from the estimate so far. Prints, per weights and
angle, the median and quartiles of the rotation error in degrees (lower is better) and the share
of pairs within 5 degrees (higher is better). A network that aligns surfaces keeps the 0-degree
start; one that does not moves away from the truth itself.

``--overlap-only`` gives the network only the overlap: each sample keeps the points within 3
median spacings of the target's points from the other sample at the truth, and is centred on its own centroid again.
What a network does there, against the whole samples, is what the part without a partner costs.
``--trim KEEP`` (networks with an overlap head) makes each pass on the head's predicted overlap:
the KEEP share of each sample the head scores best, re-centred, described and aligned alone.
``--modelnet PROTOCOL`` runs on the first ``--limit`` ModelNet40 test pairs of a protocol instead.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Iterable, Iterator, Tuple

import numpy as np

from benchmarks.eval_model import DEFAULT_DATA
from o3dsoft.bench import scan_folder
from o3dsoft.coarse import CoarseModel, cached_model
from o3dsoft.config import RegisterConfig
from o3dsoft.model import OVERLAP_SPACINGS
from o3dsoft.pair import PreparedPair
from o3dsoft.preprocess import normalise_pair, normalise_transform, point_spacing
from o3dsoft.search import network_candidates
from o3dsoft.transforms import apply_transform, axis_angle_to_matrix, rotation_angle_deg

DEFAULT_SCANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "stanford_bunny"


def overlap_only(source: np.ndarray, target: np.ndarray, T: np.ndarray, min_points: int) -> tuple:
    """The points of source (N, 3) and target (M, 3) within OVERLAP_SPACINGS median target
    spacings of the other cloud under the true T (4, 4) (target ~ T source), each centred on its
    own centroid; the whole clouds where either part would have fewer than `min_points`."""
    from scipy.spatial import cKDTree

    moved = apply_transform(T, source)
    reach = OVERLAP_SPACINGS * point_spacing(target, sample=len(target))
    keep_s = cKDTree(target).query(moved)[0] < reach
    keep_t = cKDTree(moved).query(target)[0] < reach
    if min(keep_s.sum(), keep_t.sum()) < min_points:
        return source, target
    return source[keep_s] - source[keep_s].mean(axis=0), target[keep_t] - target[keep_t].mean(axis=0)


def scan_samples(folder: Path, k: int, points: int = 1024) -> Iterator[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per pair of the scans in `folder`: the network's two samples as `register` prepares them
    (`points` per cloud), normalised, and the true T (4, 4) between them (target ~ T source)."""
    config = replace(RegisterConfig(), num_points=points)
    for p in scan_folder(folder).pairs:
        prepared = PreparedPair(p.source, p.target, config, k)
        yield (*prepared.net_normalised, normalise_transform(p.transform, prepared.norm))


def modelnet_samples(data: str, protocol: str, limit: int) -> Iterator[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The first `limit` ModelNet40 test pairs of `protocol`, normalised as in training, with their
    true T (4, 4)."""
    from o3dsoft.data import get_protocol, load_pairs

    pairs = load_pairs(data, "test", get_protocol(protocol), 0)
    for i in range(min(limit, len(pairs))):
        source, target, norm = normalise_pair(pairs[i].source, pairs[i].target)
        yield source, target, normalise_transform(pairs[i].transform, norm)


def start_rotations(rng: np.random.Generator, angles: list, R_true: np.ndarray) -> np.ndarray:
    """(A, 3, 3): the true rotation R_true (3, 3) turned further by each of `angles` (degrees)
    about a random axis."""
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return np.stack([axis_angle_to_matrix(np.radians(a) * axis) @ R_true for a, axis in zip(angles, axes)])


def errors_from_truth(
    model: CoarseModel, samples: Iterable[Tuple[np.ndarray, np.ndarray, np.ndarray]], angles: list, passes: int, seed: int, overlap: bool = False
) -> np.ndarray:
    """(P, A) rotation errors in degrees of `model` after `passes` passes, per pair of `samples`
    ((source (N, 3), target (M, 3), true T (4, 4)), normalised) and start angle (degrees from the
    truth); `overlap`: on the overlap only (:func:`overlap_only`)."""
    rng = np.random.default_rng(seed)
    errors = []
    for source, target, T in samples:
        if overlap:
            source, target = overlap_only(source, target, T, model.config.k)
        R_true = T[:3, :3]
        starts = start_rotations(rng, angles, R_true)
        for _ in range(passes):  # each pass from the rotation so far (the network centres the source itself)
            starts = network_candidates(model, source, target, starts)[:, :3, :3]
        errors.append([rotation_angle_deg(R.T @ R_true) for R in starts])
    return np.array(errors).reshape(-1, len(angles))


def eager_network(weights: str, head: bool = True):
    """The eager :class:`o3dsoft.model.SoftAlignNet` of a shipped model's name, a model file or a
    training checkpoint, in evaluation mode; without its overlap head when `head` is False (an
    alignment no head gates)."""
    from o3dsoft.model import NetConfig, SoftAlignNet
    from o3dsoft.train import _initial_weights

    state, net_config, _ = _initial_weights(weights)
    config = NetConfig.from_dict(net_config)
    if not head:
        config = replace(config, overlap=0)
        state = {name: w for name, w in state.items() if not name.startswith("overlap.")}
    net = SoftAlignNet(config)
    net.load_state_dict(state)
    return net.eval()


def trimmed_pass(net, plain, source: np.ndarray, target: np.ndarray, keep: float) -> np.ndarray:
    """One pass of an eager network with an overlap head on its predicted overlap: the head scores
    both clouds as given (source (N, 3), centred; target (M, 3)), each keeps its `keep` share of
    best-scored points, re-centred, and `plain` (the same network without its head) describes
    and aligns those alone. Returns the rotation (3, 3) of the kept source onto the kept target."""
    import torch

    f32 = lambda a: torch.as_tensor(np.ascontiguousarray(a)[None], dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        net(f32(source), f32(target))  # sets the head's logits
        kept = []
        for cloud, logits in zip((source, target), net.overlap_logits):
            scores = logits[0].numpy()
            best = cloud[scores >= np.quantile(scores, 1.0 - keep)]
            kept.append(f32(best - best.mean(axis=0)))
        R, _, _ = plain(*kept)
        return R[0].double().numpy()


def errors_with_trim(net, plain, samples: Iterable[Tuple[np.ndarray, np.ndarray, np.ndarray]], angles: list, passes: int, seed: int, keep: float) -> np.ndarray:
    """(P, A) rotation errors in degrees as :func:`errors_from_truth`, each pass a
    :func:`trimmed_pass` of the eager network `net` (one with an overlap head) and `plain`, the
    same without it."""
    rng = np.random.default_rng(seed)
    errors = []
    for source, target, T in samples:
        R_true = T[:3, :3]
        centred = source - source.mean(axis=0)
        row = []
        for R in start_rotations(rng, angles, R_true):
            for _ in range(passes):
                R = trimmed_pass(net, plain, centred @ R.T, target, keep) @ R
            row.append(rotation_angle_deg(R.T @ R_true))
        errors.append(row)
    return np.array(errors).reshape(-1, len(angles))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", nargs="+", default=["default", "incongruent", "partial"])
    parser.add_argument("--scans", type=Path, default=DEFAULT_SCANS)
    parser.add_argument("--angles", type=float, nargs="+", default=[0.0, 15.0, 30.0, 45.0, 90.0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overlap-only", action="store_true", help="give the network only the two samples' overlap at the truth")
    parser.add_argument(
        "--trim", type=float, metavar="KEEP", help="networks with an overlap head: each pass on the KEEP share of each cloud the head scores best"
    )
    parser.add_argument("--modelnet", metavar="PROTOCOL", help="ModelNet40 test pairs of this protocol instead of the scans")
    parser.add_argument("--limit", type=int, default=50, help="with --modelnet: the first N test pairs")
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="with --modelnet: the ModelNet40 folder")
    args = parser.parse_args()
    print("weights | start (deg from the truth) | rotation error median [q25, q75] (deg, lower is better) | within 5 deg (higher is better)")
    for weights in args.weights:
        model = cached_model(weights, "cpu")
        samples = modelnet_samples(args.data, args.modelnet, args.limit) if args.modelnet else scan_samples(args.scans, model.config.k)
        if args.trim is not None:
            errors = errors_with_trim(eager_network(weights), eager_network(weights, head=False), samples, args.angles, args.passes, args.seed, args.trim)
        else:
            errors = errors_from_truth(model, samples, args.angles, args.passes, args.seed, args.overlap_only)
        for j, angle in enumerate(args.angles):
            e = errors[:, j]
            print(f"{weights} | {angle:g} | {np.median(e):.1f} [{np.quantile(e, 0.25):.1f}, {np.quantile(e, 0.75):.1f}] | {100 * np.mean(e < 5):.1f} %")


if __name__ == "__main__":
    main()
