"""Training of the soft-alignment network on ModelNet40 pairs, resumable from checkpoints.

The network learns in the same normalised frame the pipeline feeds it (each cloud centred on its
own centroid, one common scale; :mod:`o3dsoft.preprocess`), so that training and inference see
the same inputs. Loss, optimiser and batch size default to the paper's.
"""

from __future__ import annotations

import json
import math
import os
import signal
import sys
import threading
import time
import traceback
import warnings
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch

from .coarse import export_torchscript, non_finite_weight, sha256_of, torch_device
from .configfile import read_config, write_config
from .data import (
    DEFAULT_POINTS_PER_SHAPE,
    Pair,
    PairDataset,
    Protocol,
    Shapes,
    check_training_recipe,
    evaluation_protocol,
    folder_fingerprint,
    load_pairs,
    resolve_data_root,
    training_parts,
)
from .errors import InputError, O3dsoftError, OutOfRange, UsageError, refuse_out_of_range
from .io import atomic_output, make_folder, remove_stale_temporaries
from .metrics import pair_errors, summarise
from .model import NetConfig, SoftAlignNet, count_parameters, match_loss, overlap_labels, overlap_loss, registration_loss, virtual_point_loss
from .preprocess import denormalise_transform, normalisation_for, normalise_pair, normalise_transform
from .transforms import rigid

RUN_FILES = ("checkpoint.pt", "model.pt", "model_card.json", "config.json", "config.yaml")  # what a run folder holds


@dataclass
class TrainConfig:
    """Every setting of a training run; saved next to its outputs.

    Attributes:
        data: ModelNet40 folder (None: $O3DSOFT_DATA).
        protocol: pair protocol for training, or a mixture of protocols (``o3dsoft.data.MIXTURES``:
            each batch from one of its protocols); evaluation uses the protocol, or the mixture's
            evaluation protocol.
        epochs, batch_size, lr: the paper's 5, 10, 1e-3 by default.
        lr_schedule: "constant" (the paper's) or "cosine" (per step from ``lr`` down to ``lr_min``
            at the end of the last epoch).
        lr_min: final learning rate of the cosine schedule.
        grad_clip: clip the gradients' total L2 norm to this value (None: no clipping, the paper's).
        point_loss: weight of :func:`o3dsoft.model.virtual_point_loss` added to the paper's loss
            (0: the paper's loss alone).
        match_loss: weight of :func:`o3dsoft.model.match_loss` (the soft assignment's cross-entropy
            against the true neighbourhoods) added to the loss (0: none).
        overlap_loss: weight of :func:`o3dsoft.model.overlap_loss` (the overlap head's
            cross-entropy against which points lie in the overlap) added to the loss (0: none;
            needs ``net.overlap``).
        only_overlap: train the overlap head alone; the rest of the network keeps its initial
            weights and BatchNorm statistics.
        init_temperature: set the softmax temperature tau to this value before training (None:
            keep the initial weights' tau). A network trained on the transform loss alone ends with
            a large tau, whose near-uniform soft partners the match loss sharpens only slowly.
        init: start from the model weights of this training checkpoint instead of a random
            initialisation (fine-tuning; optimiser and schedule start fresh). Its network must
            have this run's settings, except ``net.relative``.
        seed: fixes model initialisation, pair draws and the order of pairs.
        device: "cpu" or "cuda".
        out: output folder (checkpoint, model, card).
        checkpoint_minutes: wall-clock interval between checkpoints (also written each epoch).
        eval_pairs: test pairs evaluated after each epoch (0: none; None: the whole split).
        max_steps: stop after this many optimiser steps in total (None: run all epochs).
        max_minutes: stop after this many minutes of training in this call, with a checkpoint
            and the model exported (``--resume`` goes on): for a machine lent for a fixed time
            (None: no limit).
        limit_train: use only the first N training shapes (None: all).
        points_per_shape: points per shape (the first N of the HDF5 data, N samples on meshes).
        extra_data: a second dataset in the same layout (e.g. ``benchmarks.make_shapes``'s
            synthetic scan-like objects) whose pairs make a share of the batches (None: none).
            Epochs still count the first dataset's shapes; the second's are drawn by index
            modulo its size. Evaluation stays on the first dataset.
        extra_protocol: protocol or mixture of the second dataset's pairs.
        extra_share: share of the batches drawn from the second dataset (0 < share < 1).
        extra_points_per_shape: points per shape of the second dataset.
        workers: DataLoader worker processes making pairs (0: in the training process).
        net: architecture.
    """

    data: Optional[str] = None
    protocol: str = "paper"
    epochs: int = 5
    batch_size: int = 10
    lr: float = 1e-3
    lr_schedule: str = "constant"
    lr_min: float = 1e-5
    grad_clip: Optional[float] = None
    point_loss: float = 0.0
    match_loss: float = 0.0
    overlap_loss: float = 0.0
    only_overlap: bool = False
    init_temperature: Optional[float] = None
    init: Optional[str] = None
    seed: int = 0
    device: str = "cpu"
    out: str = "runs/train"
    checkpoint_minutes: float = 5.0
    eval_pairs: Optional[int] = 300
    max_steps: Optional[int] = None
    max_minutes: Optional[float] = None
    limit_train: Optional[int] = None
    points_per_shape: Optional[int] = DEFAULT_POINTS_PER_SHAPE
    extra_data: Optional[str] = None
    extra_protocol: str = "incongruent-far-view"
    extra_share: float = 0.5
    extra_points_per_shape: Optional[int] = DEFAULT_POINTS_PER_SHAPE
    workers: int = 0
    net: NetConfig = field(default_factory=NetConfig)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["net"] = self.net.to_dict()
        return d

    def validate(self) -> None:
        """InputError naming the first setting out of its range."""
        self.net.validate()
        check_training_recipe(self.protocol)
        check_training_recipe(self.extra_protocol)
        checks = [
            ("epochs", self.epochs >= 1, "at least 1"),
            ("batch_size", self.batch_size >= 1, "at least 1"),
            ("lr", self.lr > 0, "positive"),
            ("lr_schedule", self.lr_schedule in LR_SCHEDULES, f"one of {', '.join(LR_SCHEDULES)}"),
            ("lr_min", self.lr_schedule != "cosine" or 0 <= self.lr_min <= self.lr, "between 0 and lr"),
            ("grad_clip", self.grad_clip is None or self.grad_clip > 0, "positive or null"),
            ("point_loss", self.point_loss >= 0, "at least 0"),
            ("match_loss", self.match_loss >= 0, "at least 0"),
            (
                "overlap_loss",
                self.overlap_loss >= 0 and (self.overlap_loss == 0 or self.net.overlap > 0),
                "at least 0, and 0 without an overlap head (net.overlap)",
            ),
            ("only_overlap", not self.only_overlap or self.net.overlap > 0, "false without an overlap head (net.overlap)"),
            ("init_temperature", self.init_temperature is None or self.init_temperature > 0, "positive or null"),
            ("checkpoint_minutes", self.checkpoint_minutes > 0, "positive"),
            ("eval_pairs", self.eval_pairs is None or self.eval_pairs >= 0, "0 or more, or null for the whole split"),
            ("max_steps", self.max_steps is None or self.max_steps >= 1, "at least 1 or null"),
            ("max_minutes", self.max_minutes is None or self.max_minutes > 0, "positive or null"),
            ("limit_train", self.limit_train is None or self.limit_train >= 1, "at least 1 or null"),
            ("points_per_shape", self.points_per_shape is None or self.points_per_shape >= self.net.k, f"at least k = {self.net.k} or null"),
            ("extra_share", 0 < self.extra_share < 1, "between 0 and 1 (both excluded)"),
            (
                "extra_points_per_shape",
                self.extra_points_per_shape is None or self.extra_points_per_shape >= self.net.k,
                f"at least k = {self.net.k} or null",
            ),
            ("workers", self.workers >= 0, "0 or more"),
        ]
        refuse_out_of_range(self, checks, "training")


def normalised_batch(pairs: Sequence[Pair]):
    """Collate pairs into normalised tensors: source (B, N, 3), target (B, M, 3), R (B, 3, 3), t (B, 3)."""
    srcs, tgts, Rs, ts = [], [], [], []
    for p in pairs:
        s, t, norm = normalise_pair(p.source, p.target)
        T = normalise_transform(p.transform, norm)
        srcs.append(s)
        tgts.append(t)
        Rs.append(T[:3, :3])
        ts.append(T[:3, 3])
    f32 = lambda a: torch.as_tensor(np.stack(a), dtype=torch.float32)  # noqa: E731
    return f32(srcs), f32(tgts), f32(Rs), f32(ts)


def _save_atomic(obj, path: Path) -> None:
    with atomic_output(path) as tmp:
        torch.save(obj, tmp)


def evaluate(model: SoftAlignNet, pairs: PairDataset, limit: Optional[int], device: torch.device, batch_size: int = 10) -> Dict[str, float]:
    """Coarse-stage errors of `model` on the first `limit` pairs (in the original frame)."""
    n = len(pairs) if limit is None else min(limit, len(pairs))
    was_training = model.training
    model.eval()
    errors = []
    with torch.no_grad():
        for s in range(0, n, batch_size):
            batch = [pairs[i] for i in range(s, min(n, s + batch_size))]
            src, tgt, _, _ = normalised_batch(batch)
            R, t, _ = model(src.to(device), tgt.to(device))
            for j, p in enumerate(batch):
                T_norm = rigid(R[j].double().cpu().numpy(), t[j].double().cpu().numpy())
                T = denormalise_transform(T_norm, normalisation_for(p.source, p.target))
                errors.append(pair_errors(T, p.transform))
    model.train(was_training)
    return summarise(errors)


def _load_checkpoint(path: Path) -> dict:
    """A training checkpoint, on the CPU (the optimiser moves its state to the parameters' device)."""
    try:
        with warnings.catch_warnings():  # torch warns before failing over to jit.load on exported models
            warnings.simplefilter("ignore", UserWarning)
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for truncated or foreign files
        raise InputError(f"{path}: unreadable checkpoint ({e})") from None
    if not isinstance(ckpt, dict) or not {"model", "config", "state"} <= set(ckpt):
        raise InputError(f"{path}: not an o3dsoft training checkpoint (expected the checkpoint.pt of a run folder, not an exported model)")
    with _damaged(path):
        bad = non_finite_weight(ckpt["model"])  # NaN weights would fail only later, deep in a training step
    if bad is not None:
        raise InputError(f"{path}: the weights {bad} hold NaN or infinite values")
    return ckpt


@contextmanager
def _damaged(path: Path) -> Iterator[None]:
    """Errors from a checkpoint's contents (missing keys, wrong shapes, a bad RNG state) as one
    InputError naming the file."""
    try:
        yield
    except (KeyError, RuntimeError, ValueError, TypeError, IndexError) as e:
        first = (str(e).strip().splitlines() or [""])[0]
        raise InputError(f"{path}: damaged or incompatible checkpoint ({type(e).__name__}: {first})") from None


def _initial_weights(init: str) -> Tuple[dict, dict, dict]:
    """(state dict, network settings, record for the card) of what ``--init`` names: a training
    checkpoint, an exported model file, or a shipped model by name ("default", "paper")."""
    from .coarse import bundled_model_names, load_model

    path = Path(init)
    if not path.is_file() and init not in bundled_model_names():
        what = "is a folder, not a checkpoint or model file" if path.is_dir() else "no such checkpoint or model file"
        raise UsageError(f"{init}: {what} (shipped models, by name: {', '.join(bundled_model_names())})")
    if path.is_file() and _zipfile_has(path, "data.pkl") and not _zipfile_has(path, "code/"):
        ckpt = _load_checkpoint(path)
        record = {
            "checkpoint": str(init),
            "protocol": ckpt["config"]["protocol"],
            "epochs_completed": ckpt["state"]["epoch"],
            "steps": ckpt["state"]["global_step"],
            "training_seconds": round(ckpt["state"]["seconds"], 1),
            "history": ckpt["state"]["history"],
        }
        return ckpt["model"], ckpt["config"]["net"], record
    model = load_model(init)
    weights = {k: v.detach().clone() for k, v in model.module.state_dict().items()}
    record = {"model": str(model.path), "sha256": sha256_of(model.path), "info": model.meta.get("info", {})}
    return weights, model.meta["net"], record


def _zipfile_has(path: Path, name: str) -> bool:
    """True when the zip archive at `path` (torch's file format) holds an entry whose path inside
    its top folder starts with `name`; False for anything else."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            return any(n.split("/", 1)[-1].startswith(name) for n in z.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


def _history(state: dict) -> List[dict]:
    """Each epoch's record; the epoch under way when the run stopped last, marked partial (its
    steps so far), so that a card's history agrees with its epochs_completed."""
    partial = [{**state["partial"], "partial": True}] if "partial" in state and state["step_in_epoch"] else []
    return state["history"] + partial


def checkpoint_card(checkpoint: Path) -> dict:
    """The training record of a checkpoint, for the card of a run stopped before it wrote one."""
    ckpt = _load_checkpoint(checkpoint)
    config, state = ckpt["config"], ckpt["state"]
    return {
        "config": config,
        "protocol": config["protocol"],
        "epochs_completed": state["epoch"],
        "steps": state["global_step"],
        "history": _history(state),
        "initialised_from": ckpt.get("init"),
        "training_seconds": round(state["seconds"], 1),
        "device": config["device"],
        "world_size": ckpt.get("world_size", 1),
    }


def export_checkpoint(checkpoint: Path, out: Path) -> Path:
    """Export the model of a training checkpoint to a TorchScript file with the current code."""
    ckpt = _load_checkpoint(checkpoint)
    net = NetConfig.from_dict(ckpt["config"]["net"])
    model = SoftAlignNet(net)
    model.load_state_dict(ckpt["model"])
    info = {"protocol": ckpt["config"]["protocol"], "epochs_completed": ckpt["state"]["epoch"]}
    return export_torchscript(model, net, out, info=info)


LR_SCHEDULES = ("constant", "cosine")
# Settings that fix which pairs each step sees and the network's shape: a resumed run must keep them.
RESUME_MUST_MATCH = ("data", "protocol", "batch_size", "seed", "net", "limit_train", "points_per_shape") + tuple(
    f.name for f in fields(TrainConfig) if f.name.startswith("extra_")
)


def _training_mode(model: SoftAlignNet, only_overlap: bool) -> None:
    """Training mode; with `only_overlap`, for the overlap head alone (the rest keeps its
    BatchNorm statistics)."""
    model.train(not only_overlap)
    model.overlap.train()


def _lr_factor(config: TrainConfig, total_steps: int) -> Callable[[int], float]:
    """Multiplier of ``config.lr`` after a given number of optimiser steps."""
    if config.lr_schedule == "constant":
        return lambda step: 1.0
    floor = config.lr_min / config.lr

    def cosine(step: int) -> float:
        progress = min(step / max(total_steps, 1), 1.0)
        return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))

    return cosine


def _setup_distributed(config: TrainConfig) -> Tuple[int, int, torch.device]:
    """(rank, world size, device). Under torchrun (WORLD_SIZE > 1) joins the process group:
    NCCL with one GPU per process (LOCAL_RANK) for cuda, gloo for cpu."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        return 0, 1, torch.device(config.device)
    import torch.distributed as dist

    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if torch.device(config.device).type == "cuda":
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
        backend = "nccl"
    else:
        device, backend = torch.device("cpu"), "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend)
    return rank, world, device


class _TrainingPairs(torch.utils.data.Dataset):
    """Normalised tensors of protocol pairs, for torch's DataLoader (workers included), keyed by
    (shape index, part): the part names which of a mixture's protocols, over which dataset,
    makes the pair. The first part's dataset sets the length; a part over a smaller dataset
    takes the index modulo its size."""

    def __init__(self, parts: Sequence[PairDataset]) -> None:
        self.parts = list(parts)

    def __len__(self) -> int:
        return len(self.parts[0])

    def __getitem__(self, key: Tuple[int, int]):
        index, part = key
        pairs = self.parts[part]
        return tuple(x[0] for x in normalised_batch([pairs[index % len(pairs)]]))


class _Part(NamedTuple):
    """One source of training batches: a protocol over a dataset's training shapes, and its weight."""

    protocol: Protocol
    weight: float
    shapes: Shapes


def _training_sources(config: TrainConfig, train_pairs: PairDataset) -> List[_Part]:
    """Every (protocol, weight, shapes) batches are drawn from: the recipe's parts over the first
    dataset, and with `extra_data` the extra recipe's parts over it, weighted by `extra_share`."""
    parts = [_Part(p, w, train_pairs.shapes) for p, w in training_parts(config.protocol)]
    if config.extra_data is None:
        return parts
    extra = training_parts(config.extra_protocol)
    try:
        shapes = load_pairs(config.extra_data, "train", extra[0][0], config.seed, config.extra_points_per_shape).shapes
    except (InputError, UsageError) as e:
        raise type(e)(f"the second dataset (extra_data, --extra-data): {e}") from None
    return _scaled(parts, 1 - config.extra_share) + _scaled([_Part(p, w, shapes) for p, w in extra], config.extra_share)


def _scaled(parts: List[_Part], share: float) -> List[_Part]:
    """The parts with weights rescaled to sum to `share`."""
    total = sum(p.weight for p in parts)
    return [p._replace(weight=share * p.weight / total) for p in parts]


def _batches(order: Sequence[int], first_batch: int, batch_size: int, weights: Sequence[float], seed: int, epoch: int) -> List[List[Tuple[int, int]]]:
    """Split shape indices into batches of (index, part) keys, every batch from one part.

    Batch b's part is drawn from a generator seeded by (seed, epoch, b) alone, so a resumed run
    (which starts at batch `first_batch`) sees the same batches as an uninterrupted one.
    """
    p = np.asarray(weights, dtype=np.float64) / np.sum(weights)
    out = []
    for j in range(len(order) // batch_size):
        b = first_batch + j
        part = int(np.random.default_rng([seed, epoch, b]).choice(len(p), p=p)) if len(p) > 1 else 0
        out.append([(int(i), part) for i in order[j * batch_size : (j + 1) * batch_size]])
    return out


def _replicas_identical(model: torch.nn.Module) -> bool:
    """True when every rank holds the same parameters (a check that DDP kept them in step)."""
    import torch.distributed as dist

    flat = torch.cat([p.detach().reshape(-1).float() for p in model.parameters()])  # on the device: NCCL has no CPU tensors
    gathered = [torch.empty_like(flat) for _ in range(dist.get_world_size())]
    dist.all_gather(gathered, flat)
    return all(torch.equal(gathered[0], g) for g in gathered[1:])


def settings_from(
    given: Dict[str, Any],
    defaults: Dict[str, Any],
    config_file: Optional[Path] = None,
    net: Optional[Dict[str, Any]] = None,
    resume: bool = False,
) -> TrainConfig:
    """A run's settings, each from the first that has it: `given` (e.g. options typed on a command
    line), the YAML `config_file` (when resuming without one, the run folder's own config.yaml),
    `defaults`. `net`: NetConfig fields to override.

    Raises:
        InputError: the file is unreadable, has unknown or mistyped keys, or the settings are invalid.
    """
    out = Path(given.get("out", defaults.get("out", TrainConfig.out)))
    if resume and config_file is None and (out / "config.yaml").is_file():
        config_file = out / "config.yaml"
    lines: Dict[str, int] = {}
    settings = read_config(config_file, TrainConfig, lines) if config_file else {}
    settings = {**defaults, **settings, **given}
    network = settings.pop("net", NetConfig())
    config = TrainConfig(net=replace(network, **(net or {})), **settings)
    try:
        config.validate()
    except OutOfRange as e:  # a value the file gives: named with its line
        if e.field in lines and e.field not in given:
            raise InputError(f"{config_file} line {lines[e.field]}: {e}") from None
        raise
    return config


def train(config: TrainConfig, resume: bool = False, log: Callable[[str], None] = print, overwrite: bool = False) -> Path:
    """Train, checkpoint, evaluate, and export TorchScript + model card into ``config.out``.

    Under ``torchrun --nproc_per_node P`` the same call trains with DistributedDataParallel: each
    process draws its own share of every epoch's pairs (batch_size pairs per process and step)
    and only rank 0 logs, evaluates and writes files.

    Args:
        resume: go on from ``config.out``'s checkpoint.
        overwrite: start a new run in a folder that holds one (its files are replaced).
    Returns:
        The path of the exported model file.
    Raises:
        UsageError: ``config.out`` holds a run and neither `resume` nor `overwrite` is set, or
            `resume` is set and it holds no checkpoint; the device is not on this machine.
    """
    config.validate()
    torch_device(config.device)
    held = [name for name in RUN_FILES if (Path(config.out) / name).exists()]
    saved = "checkpoint.pt" in held  # a run stopped before its first checkpoint left its settings only
    if held and not (resume or overwrite):
        go_on = "--resume goes on with it, " if saved else ""
        what = "a training run" if saved or "model.pt" in held else "the settings of a run stopped before its first checkpoint"
        raise UsageError(f"{config.out}: holds {what} ({', '.join(held)}); {go_on}--overwrite starts a new one there, or choose another --out")
    if resume and not saved:  # before the data: with no checkpoint there is nothing to go on with
        started = " (a run stopped before its first checkpoint: --overwrite starts it again)" if held else ""
        raise UsageError(f"{Path(config.out) / 'checkpoint.pt'}: no checkpoint to resume from{started}")
    rank, world, device = _setup_distributed(config)
    try:
        return _train(config, resume, log if rank == 0 else (lambda message: None), rank, world, device)
    except BaseException as e:
        traceback.clear_frames(e.__traceback__)  # the frames would keep the DDP wrapper alive
        raise
    finally:
        if world > 1:
            _teardown_distributed()


def _data_fingerprints(config: TrainConfig) -> Dict[str, Optional[str]]:
    """:func:`~o3dsoft.data.folder_fingerprint` of the run's data folder (``data``, else
    $O3DSOFT_DATA) and of ``extra_data`` (None where not given): the data a resumed run must
    keep, wherever it lies now (a run trained on a lent GPU machine goes on here)."""
    return {
        "data": folder_fingerprint(resolve_data_root(config.data)),
        "extra_data": folder_fingerprint(resolve_data_root(config.extra_data, "--extra-data")) if config.extra_data else None,
    }


def _teardown_distributed() -> None:
    """Destroy the process group after everything that used it (the DDP wrapper, its reducer) is freed.

    Freeing the wrapper only at interpreter exit, after the group is gone, can abort the process
    ("terminate called without an active exception") from one of gloo's threads.
    """
    import gc

    import torch.distributed as dist

    gc.collect()
    if dist.is_initialized():
        dist.destroy_process_group()


def _out_of_steps(config: TrainConfig, state: Dict[str, Any]) -> bool:
    """The run has taken its ``max_steps`` (None: no limit)."""
    return config.max_steps is not None and state["global_step"] >= config.max_steps


def _resume_checkpoint(path: Path, config: TrainConfig, world: int, fingerprints: Dict[str, Optional[str]]) -> dict:
    """The checkpoint to resume from, refused when its run's settings, its data (`fingerprints`:
    :func:`_data_fingerprints` of this run's) or its process count differ."""
    ckpt = _load_checkpoint(path)  # a missing one: train() refused the run before this
    saved = dict(ckpt["config"], net=NetConfig.from_dict(ckpt["config"]["net"]).to_dict())  # with settings added since
    by_content = "data_fingerprints" in ckpt  # the data compared by its files, not by how its path is written
    names = [k for k in RESUME_MUST_MATCH if not (by_content and k in ("data", "extra_data"))]
    mismatched = [k for k in names if saved.get(k, TrainConfig().to_dict()[k]) != config.to_dict()[k]]
    if by_content:
        mismatched += [k for k in ("data", "extra_data") if ckpt["data_fingerprints"].get(k) != fingerprints[k]]
    if mismatched:
        raise InputError(f"{path}: cannot resume with a different {', '.join(mismatched)} than the checkpoint's")
    if ckpt.get("world_size", 1) != world:
        raise InputError(f"{path}: written by {ckpt.get('world_size', 1)} processes, cannot resume with {world}")
    return ckpt


def _splits(config: TrainConfig, protocol) -> Tuple[PairDataset, Optional[PairDataset]]:
    """The training pairs (the first `limit_train` shapes, if set) and the evaluation pairs (None
    when `eval_pairs` is 0). Every rank loads both, so that a missing split stops them all alike."""
    train_pairs = load_pairs(config.data, "train", protocol, config.seed, config.points_per_shape)
    if config.limit_train is not None:
        train_pairs.shapes = train_pairs.shapes._replace(
            points=train_pairs.shapes.points[: config.limit_train], labels=train_pairs.shapes.labels[: config.limit_train]
        )
    if config.eval_pairs == 0:
        return train_pairs, None
    test_pairs = load_pairs(config.data, "test", evaluation_protocol(config.protocol), config.seed + 1, config.points_per_shape)
    if len(test_pairs) == 0:
        raise InputError(f"{config.data}: the test split has no shapes for protocol {config.protocol!r}; use --eval-pairs 0")
    return train_pairs, test_pairs


def _write_settings(out: Path, config: TrainConfig, fresh: bool) -> None:
    """The settings actually used, as config.json and config.yaml in the run folder; a `fresh`
    run first removes an earlier run's files there, so that none outlives it unreplaced."""
    make_folder(out)
    remove_stale_temporaries(out, RUN_FILES)
    if fresh:
        for name in RUN_FILES:
            (out / name).unlink(missing_ok=True)
    with atomic_output(out / "config.json") as tmp:
        tmp.write_text(json.dumps(config.to_dict(), indent=2))
    with atomic_output(out / "config.yaml") as tmp:
        write_config(tmp, config.to_dict())


def _evaluation_line(epoch: int, m: Dict[str, float]) -> str:
    return (
        f"epoch {epoch + 1}: {int(m['pairs'])} test pairs, network alone: rotation error median "
        f"{m['rotation_deg_median']:.3f} deg, mean {m['rotation_deg_mean']:.3f} deg; translation error median "
        f"{m['translation_median']:.4f} units; recall (5 deg, 0.05) {100 * m['recall_5deg']:.1f} % "
        "(errors: lower is better; recall: higher is better)"
    )


def _card_facts(config: TrainConfig, train_pairs: PairDataset, parts, state: dict) -> dict:
    """What the model card says about the data, the protocol and the progress of the run."""
    shapes = train_pairs.shapes.points
    root = resolve_data_root(config.data)  # $O3DSOFT_DATA's where none was given
    dataset = f"train split of {root} ({shapes.shape[0]} shapes, {shapes.shape[1]} points each)"
    if config.limit_train:
        dataset += f", first {config.limit_train} shapes"
    if config.extra_data is not None:
        extra = parts[-1].shapes.points
        dataset += f"; {100 * config.extra_share:.0f} % of the batches from the train split of {config.extra_data} ({extra.shape[0]} shapes, {extra.shape[1]} points each)"
    described = [{**asdict(p.protocol), "weight": p.weight, "shapes": len(p.shapes.points)} for p in parts]
    return {
        "config": config.to_dict(),
        "dataset": dataset,
        "evaluated_on": f"test split of {root}, first {config.eval_pairs} pairs of the protocol (seed {config.seed + 1})" if config.eval_pairs else None,
        "protocol": asdict(parts[0].protocol) if len(parts) == 1 else {"mixture": described},
        "epochs_completed": state["epoch"],
        "steps": state["global_step"],
        "history": _history(state),
        "training_seconds": round(state["seconds"], 1),
    }


def _train(config: TrainConfig, resume: bool, log: Callable[[str], None], rank: int, world: int, device: torch.device) -> Path:
    lead = rank == 0
    out = Path(config.out)
    ckpt_path = out / "checkpoint.pt"
    protocol = training_parts(config.protocol)[0][0]  # which split's categories the run uses; every part of a mixture uses all

    torch.manual_seed(config.seed)
    model = SoftAlignNet(config.net).to(device)
    if config.only_overlap:
        for name, p in model.named_parameters():
            p.requires_grad_(name.startswith("overlap."))
    optimiser = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr)
    init_record = None
    if config.init is not None and not resume:
        weights, init_net, init_record = _initial_weights(config.init)
        # The relative first layer has the same parameters as the absolute one, and a network
        # without an overlap head starts one with a new head: a network can start from either.
        init_config = NetConfig.from_dict(init_net)
        new_head = init_config.overlap == 0 and config.net.overlap > 0
        adopted = {"relative": config.net.relative}
        if new_head:
            adopted.update(overlap=config.net.overlap, overlap_layers=config.net.overlap_layers)
        if replace(init_config, **adopted) != config.net:
            theirs, ours = replace(init_config, **adopted).to_dict(), config.net.to_dict()
            differ = ", ".join(f"{k} {theirs[k]!r} (this run: {ours[k]!r})" for k in ours if theirs[k] != ours[k])
            raise InputError(f"{config.init}: its network settings differ from this run's: {differ}")
        with _damaged(Path(config.init)):
            missing, unexpected = model.load_state_dict(weights, strict=not new_head)
            if unexpected or any(not k.startswith("overlap.") for k in missing):
                raise KeyError(f"weights do not fit the network: missing {missing}, unexpected {unexpected}")
    if config.init_temperature is not None and not resume:
        with torch.no_grad():
            model.log_tau.fill_(math.log(config.init_temperature))
    state = {"epoch": 0, "step_in_epoch": 0, "global_step": 0, "history": [], "seconds": 0.0}
    ckpt: dict = {}
    fingerprints = _data_fingerprints(config) if lead or resume else {}  # what a resumed run must keep, and what rank 0 checkpoints
    if resume:
        ckpt = _resume_checkpoint(ckpt_path, config, world, fingerprints)
        with _damaged(ckpt_path):
            model.load_state_dict(ckpt["model"])
            missing = set(state) - set(ckpt["state"])
            if missing:
                raise KeyError(f"state lacks {', '.join(sorted(missing))}")
            state = ckpt["state"]
            init_record = ckpt.get("init")
            torch.set_rng_state(ckpt["torch_rng"])
    finished = _out_of_steps(config, state) or state["epoch"] >= config.epochs  # resumed at its end: nothing to train, said below
    if resume and not finished:
        log(f"resumed at epoch {state['epoch'] + 1}, step {state['step_in_epoch']}")

    train_pairs, test_pairs = _splits(config, protocol)
    parts = _training_sources(config, train_pairs)
    if not lead:
        test_pairs = None
    steps_per_epoch = len(train_pairs) // world // config.batch_size
    if steps_per_epoch == 0:
        raise InputError(f"the training split has {len(train_pairs)} shapes, fewer than one batch of {config.batch_size} per process")
    total_steps = config.epochs * steps_per_epoch
    schedule = _lr_factor(config, total_steps)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, schedule)
    if resume:
        # After the scheduler's construction, which resets the learning rate to the schedule's start.
        with _damaged(ckpt_path):
            optimiser.load_state_dict(ckpt["optimiser"])
            if "scheduler" in ckpt:  # checkpoints of earlier versions had none (constant lr)
                scheduler.load_state_dict(ckpt["scheduler"])
            else:
                scheduler.last_epoch = state["global_step"]
        # The states bring back the saved learning rate; the run goes on at this call's (--lr
        # given with --resume), on the schedule of this call's epochs, from the step it is at.
        scheduler.base_lrs = [config.lr] * len(optimiser.param_groups)
        for group in optimiser.param_groups:
            group["initial_lr"] = config.lr
            group["lr"] = config.lr * schedule(scheduler.last_epoch)
    if lead and not finished:  # a finished run keeps the settings it was trained with
        _write_settings(out, config, fresh=not resume)
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)

    def export(identical: Optional[bool]) -> None:
        """model.pt and model_card.json of the weights so far (rank 0)."""
        model_path = export_torchscript(model, config.net, out / "model.pt", info={"protocol": config.protocol, "epochs_completed": state["epoch"]})
        card = {
            "model_file": model_path.name,
            "sha256": sha256_of(model_path),
            **_card_facts(config, train_pairs, parts, state),
            "initialised_from": init_record,
            "parameters": sum(p.numel() for p in model.parameters()),
            "trained_parameters": count_parameters(model),  # fewer with only_overlap
            "torch_version": torch.__version__,
            "device": str(device),
            "world_size": world,
            "replicas_identical": identical,
        }
        with atomic_output(out / "model_card.json") as tmp:
            tmp.write_text(json.dumps(card, indent=2))
        log(f"wrote {model_path} and {out / 'model_card.json'}")

    def checkpoint() -> None:
        if not lead:
            return
        contents = {
            "model": model.state_dict(),
            "optimiser": optimiser.state_dict(),
            "scheduler": scheduler.state_dict(),
            "init": init_record,
            "state": state,
            "torch_rng": torch.get_rng_state(),
            "config": config.to_dict(),
            "world_size": world,
            "data_fingerprints": fingerprints,
        }
        try:
            _save_atomic(contents, ckpt_path)
        except (OSError, RuntimeError, InputError) as e:  # torch.save reports a failed write as RuntimeError
            if ckpt_path.is_file():
                advice = "the previous checkpoint is unchanged; once the folder is writable again (space, permissions), go on with --resume"
            else:
                advice = "no checkpoint was written; once the folder is writable again (space, permissions), start the run again with --overwrite"
            raise O3dsoftError(f"{ckpt_path}: could not write the checkpoint ({e}); {advice}") from None

    done = _out_of_steps(config, state)
    if finished:
        reached = f"max_steps = {config.max_steps}" if done else f"its {config.epochs} epochs"
        kept = _exported_at(out, state["global_step"])
        log(
            f"the run has already reached {reached} (step {state['global_step']}): nothing to train; "
            + ("its files are left as they are" if kept else "its model is exported")
            + ". Raise --max-steps or --epochs to go on"
        )
        if kept:
            return out / "model.pt"
    dataset = _TrainingPairs([train_pairs])
    stop = _StopBetweenSteps(world == 1)
    last_ckpt = started = time.monotonic()
    try:
        while state["epoch"] < config.epochs and not done:
            epoch = state["epoch"]
            # Pairs of epoch e differ from those of other epochs (seeded by epoch) but repeat on resume.
            dataset.parts = [PairDataset(part.shapes, part.protocol, seed=config.seed * 1000 + epoch) for part in parts]
            sampler = torch.utils.data.DistributedSampler(dataset, num_replicas=world, rank=rank, shuffle=True, seed=config.seed, drop_last=True)
            sampler.set_epoch(epoch)
            order = list(sampler)[state["step_in_epoch"] * config.batch_size : steps_per_epoch * config.batch_size]
            batches = _batches(order, state["step_in_epoch"], config.batch_size, [part.weight for part in parts], config.seed + 1000 * rank, epoch)
            loader = torch.utils.data.DataLoader(dataset, batch_sampler=batches, num_workers=config.workers)
            losses: List[float] = state.get("epoch_losses", [])
            progress = _Progress(lead, epoch, config, steps_per_epoch, state["step_in_epoch"], world, log)
            _training_mode(model, config.only_overlap)
            for src, tgt, R_gt, t_gt in loader:
                src, tgt, R_gt, t_gt = (x.to(device, non_blocking=True) for x in (src, tgt, R_gt, t_gt))
                R, t, _ = net(src, tgt)
                loss = registration_loss(R, t, R_gt, t_gt)
                if config.point_loss > 0:
                    loss = loss + config.point_loss * virtual_point_loss(src, tgt, model.virtual_points, R_gt, t_gt)
                if config.match_loss > 0:
                    loss = loss + config.match_loss * match_loss(src, tgt, model.soft_partners, R_gt, t_gt)
                if config.overlap_loss > 0:
                    loss = loss + config.overlap_loss * overlap_loss(model.overlap_logits, overlap_labels(src, tgt, R_gt, t_gt))
                optimiser.zero_grad(set_to_none=True)
                loss.backward()
                if config.grad_clip is not None:
                    torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
                optimiser.step()
                scheduler.step()
                losses.append(loss.item())
                state["step_in_epoch"] += 1
                state["global_step"] += 1
                state["epoch_losses"] = losses
                progress.update(losses, scheduler.get_last_lr()[0])
                if stop.asked or time.monotonic() - last_ckpt > config.checkpoint_minutes * 60:
                    state["partial"] = _epoch_record(epoch, losses)  # the epoch so far, for the card's history should the run stop here
                    state["seconds"] += time.monotonic() - last_ckpt
                    last_ckpt = time.monotonic()
                    checkpoint()
                if stop.asked:
                    log(f"interrupted: checkpoint after step {state['global_step']} in {ckpt_path} (--resume goes on from there)")
                    export(None)  # the model so far, usable at once (a second Ctrl-C stops without it)
                    raise KeyboardInterrupt
                out_of_steps = _out_of_steps(config, state)
                out_of_time = config.max_minutes is not None and time.monotonic() - started >= config.max_minutes * 60
                if out_of_steps or out_of_time:
                    if not out_of_steps:
                        log(f"stopped: max_minutes = {config.max_minutes:g} of training in this call, after step {state['global_step']} (--resume goes on)")
                    done = True
                    break
            progress.close()
            record = _epoch_record(epoch, losses)
            if test_pairs is not None:
                record["test"] = evaluate(model, test_pairs, config.eval_pairs, device)
                log(_evaluation_line(epoch, record["test"]))
            if state["step_in_epoch"] >= steps_per_epoch:
                state["history"].append(record)
                state["epoch"] += 1
                state["step_in_epoch"] = 0
                state["epoch_losses"] = []
                state.pop("partial", None)
            else:
                state["partial"] = record
            state["seconds"] += time.monotonic() - last_ckpt
            last_ckpt = time.monotonic()
            checkpoint()
    finally:
        stop.restore()
    identical = None
    if world > 1:
        identical = _replicas_identical(model)
        log(f"{world} processes: replicas identical after training: {identical}")
    if lead:
        export(identical)
    if world > 1:
        import torch.distributed as dist

        dist.barrier()  # the other ranks return only once rank 0 has written the model
    return out / "model.pt"


def _exported_at(out: Path, step: int) -> bool:
    """The run folder `out` holds the model of its checkpoint's `step`: model.pt, and a card
    that gives that step and model.pt's sha256 (an export that failed or was cut short after the
    last checkpoint leaves an earlier one)."""
    try:
        card = json.loads((out / "model_card.json").read_text())
        return card.get("steps") == step and card.get("sha256") == sha256_of(out / "model.pt")
    except (OSError, ValueError):
        return False


def _epoch_record(epoch: int, losses: Sequence[float]) -> dict:
    """The history's record of epoch `epoch` (counted from 0) from its steps' losses so far."""
    return {"epoch": epoch + 1, "steps": len(losses), "train_loss": float(np.mean(losses)) if losses else math.nan}


class _StopBetweenSteps:
    """While training in one process: Ctrl-C or SIGTERM asks the run to stop after the step under
    way, so that a checkpoint of a whole step is written first (a second one stops at once).
    Several processes (torchrun) keep the signals' own handlers: they must stop at the same step."""

    def __init__(self, enabled: bool) -> None:
        self.asked = False
        self._before: Dict[int, Any] = {}
        if enabled and threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._before[signum] = signal.signal(signum, self._ask)

    def _ask(self, signum, frame) -> None:
        if self.asked:
            raise KeyboardInterrupt
        self.asked = True

    def restore(self) -> None:
        """The handlers from before, back in place."""
        for signum, handler in self._before.items():
            signal.signal(signum, handler)
        self._before = {}


class _Progress:
    """A progress bar (on a terminal) or a log line every 20 steps: loss, pairs/s, learning rate."""

    def __init__(self, lead: bool, epoch: int, config: TrainConfig, steps: int, start: int, world: int, log: Callable[[str], None]) -> None:
        self.epoch, self.config, self.steps, self.world, self.log = epoch, config, steps, world, log
        self.step = start
        self.t0 = time.monotonic()
        self.done_here = 0
        self.bar = None
        if lead and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=steps, initial=start, desc=f"epoch {epoch + 1}/{config.epochs}", unit="step", file=sys.stderr, dynamic_ncols=True)

    def update(self, losses: Sequence[float], lr: float) -> None:
        self.step += 1
        self.done_here += 1
        rate = self.done_here * self.config.batch_size * self.world / max(time.monotonic() - self.t0, 1e-9)
        loss = float(np.mean(losses[-20:]))
        if self.bar is not None:
            self.bar.set_postfix_str(f"loss {loss:.5f} (lower is better), {rate:.1f} pairs/s, lr {lr:.2e}", refresh=False)
            self.bar.update(1)
        elif self.step % 20 == 0 or self.step == self.steps:
            self.log(
                f"epoch {self.epoch + 1}/{self.config.epochs} step {self.step}/{self.steps} loss {loss:.5f} (lower is better), "
                f"{rate:.2f} pairs/s, lr {lr:.2e}, {(time.monotonic() - self.t0) / 60:.1f} min"
            )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
