"""Training of the soft-alignment network on ModelNet40 pairs, resumable from checkpoints.

The network learns in the same normalised frame the pipeline feeds it (each cloud centred on its
own centroid, one common scale; :mod:`o3dsoft.preprocess`), so that training and inference see
the same inputs. Loss, optimiser and batch size default to the paper's.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch

from .coarse import export_torchscript, sha256_of
from .data import Pair, PairDataset, get_protocol, load_pairs
from .errors import InputError
from .metrics import pair_errors, summarise
from .model import NetConfig, SoftAlignNet, count_parameters, registration_loss
from .preprocess import denormalise_transform, normalisation_for, normalise_pair, normalise_transform
from .transforms import rigid


@dataclass
class TrainConfig:
    """Every setting of a training run; saved next to its outputs.

    Attributes:
        data: ModelNet40 folder (None: $O3DSOFT_DATA).
        protocol: pair protocol for training and evaluation.
        epochs, batch_size, lr: the paper's 5, 10, 1e-3 by default.
        lr_schedule: "constant" (the paper's) or "cosine" (per step from ``lr`` down to ``lr_min``
            at the end of the last epoch).
        lr_min: final learning rate of the cosine schedule.
        grad_clip: clip the gradients' total L2 norm to this value (None: no clipping, the paper's).
        init: start from the model weights of this training checkpoint instead of a random
            initialisation (fine-tuning; optimiser and schedule start fresh).
        seed: fixes model initialisation, pair draws and the order of pairs.
        device: "cpu" or "cuda".
        out: output folder (checkpoint, model, card).
        checkpoint_minutes: wall-clock interval between checkpoints (also written each epoch).
        eval_pairs: test pairs evaluated after each epoch (0: none; None: the whole split).
        max_steps: stop after this many optimiser steps in total (None: run all epochs).
        limit_train: use only the first N training shapes (None: all).
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
    init: Optional[str] = None
    seed: int = 0
    device: str = "cpu"
    out: str = "runs/train"
    checkpoint_minutes: float = 5.0
    eval_pairs: Optional[int] = 300
    max_steps: Optional[int] = None
    limit_train: Optional[int] = None
    net: NetConfig = field(default_factory=NetConfig)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["net"] = self.net.to_dict()
        return d


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
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


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


def _load_checkpoint(path: Path, device: torch.device) -> dict:
    try:
        return torch.load(path, map_location=device, weights_only=False)
    except Exception as e:  # torch raises many types for truncated or foreign files
        raise InputError(f"{path}: unreadable checkpoint ({e})") from None


def export_checkpoint(checkpoint: Path, out: Path) -> Path:
    """Export the model of a training checkpoint to a TorchScript file with the current code."""
    ckpt = _load_checkpoint(checkpoint, torch.device("cpu"))
    net = NetConfig.from_dict(ckpt["config"]["net"])
    model = SoftAlignNet(net)
    model.load_state_dict(ckpt["model"])
    info = {"protocol": ckpt["config"]["protocol"], "epochs_completed": ckpt["state"]["epoch"]}
    return export_torchscript(model, net, out, info=info)


LR_SCHEDULES = ("constant", "cosine")


def _lr_factor(config: TrainConfig, total_steps: int) -> Callable[[int], float]:
    """Multiplier of ``config.lr`` after a given number of optimiser steps."""
    if config.lr_schedule == "constant":
        return lambda step: 1.0
    floor = config.lr_min / config.lr

    def cosine(step: int) -> float:
        progress = min(step / max(total_steps, 1), 1.0)
        return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))

    return cosine


def train(config: TrainConfig, resume: bool = False, log: Callable[[str], None] = print) -> Path:
    """Train, checkpoint, evaluate, and export TorchScript + model card into ``config.out``.

    Returns:
        The path of the exported model file.
    """
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    device = torch.device(config.device)
    protocol = get_protocol(config.protocol)

    torch.manual_seed(config.seed)
    model = SoftAlignNet(config.net).to(device)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr)
    if config.lr_schedule not in LR_SCHEDULES:
        raise InputError(f"unknown lr_schedule {config.lr_schedule!r}; expected one of {', '.join(LR_SCHEDULES)}")
    init_record = None
    if config.init is not None and not resume:
        init_ckpt = _load_checkpoint(Path(config.init), device)
        if init_ckpt["config"]["net"] != config.net.to_dict():
            raise InputError(f"{config.init}: its network settings differ from this run's ({init_ckpt['config']['net']})")
        model.load_state_dict(init_ckpt["model"])
        init_record = {"checkpoint": str(config.init), "protocol": init_ckpt["config"]["protocol"],
                       "epochs_completed": init_ckpt["state"]["epoch"], "steps": init_ckpt["state"]["global_step"],
                       "training_seconds": round(init_ckpt["state"]["seconds"], 1), "history": init_ckpt["state"]["history"]}
    state = {"epoch": 0, "step_in_epoch": 0, "global_step": 0, "history": [], "seconds": 0.0}
    if resume:
        if not ckpt_path.is_file():
            raise InputError(f"{ckpt_path}: no checkpoint to resume from")
        ckpt = _load_checkpoint(ckpt_path, device)
        saved = ckpt["config"]
        mismatched = [k for k in ("protocol", "batch_size", "seed", "net") if saved.get(k) != config.to_dict()[k]]
        if mismatched:
            raise InputError(f"{ckpt_path}: cannot resume with a different {', '.join(mismatched)} than the checkpoint's")
        model.load_state_dict(ckpt["model"])
        state = ckpt["state"]
        init_record = ckpt.get("init")
        torch.set_rng_state(ckpt["torch_rng"])
        log(f"resumed at epoch {state['epoch'] + 1}, step {state['step_in_epoch']}")
    (out / "config.json").write_text(json.dumps(config.to_dict(), indent=2))

    train_pairs = load_pairs(config.data, "train", protocol, config.seed)
    if config.limit_train is not None:
        train_pairs.shapes = train_pairs.shapes._replace(
            points=train_pairs.shapes.points[: config.limit_train], labels=train_pairs.shapes.labels[: config.limit_train]
        )
    test_pairs = load_pairs(config.data, "test", protocol, config.seed + 1) if config.eval_pairs != 0 else None
    steps_per_epoch = len(train_pairs) // config.batch_size
    if steps_per_epoch == 0:
        raise InputError(f"the training split has {len(train_pairs)} shapes, fewer than one batch of {config.batch_size}")
    total_steps = config.epochs * steps_per_epoch
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, _lr_factor(config, total_steps))
    if resume:
        # After the scheduler's construction, which resets the learning rate to the schedule's start.
        optimiser.load_state_dict(ckpt["optimiser"])
        if "scheduler" in ckpt:  # checkpoints of earlier versions had none (constant lr)
            scheduler.load_state_dict(ckpt["scheduler"])

    def checkpoint() -> None:
        _save_atomic(
            {
                "model": model.state_dict(),
                "optimiser": optimiser.state_dict(),
                "scheduler": scheduler.state_dict(),
                "init": init_record,
                "state": state,
                "torch_rng": torch.get_rng_state(),
                "config": config.to_dict(),
            },
            ckpt_path,
        )

    model.train()
    last_ckpt = time.monotonic()
    done = False
    while state["epoch"] < config.epochs and not done:
        epoch = state["epoch"]
        # Pairs of epoch e differ from those of other epochs (seeded by epoch) but repeat on resume.
        order = np.random.default_rng([config.seed, epoch]).permutation(len(train_pairs))
        epoch_view = PairDataset(train_pairs.shapes, protocol, seed=config.seed * 1000 + epoch)
        losses: List[float] = state.get("epoch_losses", [])
        t0 = time.monotonic()
        for step in range(state["step_in_epoch"], steps_per_epoch):
            batch = [epoch_view[int(i)] for i in order[step * config.batch_size : (step + 1) * config.batch_size]]
            src, tgt, R_gt, t_gt = (x.to(device) for x in normalised_batch(batch))
            R, t, _ = model(src, tgt)
            loss = registration_loss(R, t, R_gt, t_gt)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            if config.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimiser.step()
            scheduler.step()
            losses.append(loss.item())
            state["step_in_epoch"] = step + 1
            state["global_step"] += 1
            state["epoch_losses"] = losses
            if (step + 1) % 20 == 0 or step + 1 == steps_per_epoch:
                elapsed = time.monotonic() - t0
                log(
                    f"epoch {epoch + 1}/{config.epochs} step {step + 1}/{steps_per_epoch} "
                    f"loss {np.mean(losses[-20:]):.5f} (lower is better), lr {scheduler.get_last_lr()[0]:.2e}"
                    f" | {elapsed / 60:.1f} min this session"
                )
            if time.monotonic() - last_ckpt > config.checkpoint_minutes * 60:
                state["seconds"] += time.monotonic() - last_ckpt
                last_ckpt = time.monotonic()
                checkpoint()
            if config.max_steps is not None and state["global_step"] >= config.max_steps:
                done = True
                break
        record = {"epoch": epoch + 1, "steps": len(losses), "train_loss": float(np.mean(losses)) if losses else math.nan}
        if test_pairs is not None:
            record["test"] = evaluate(model, test_pairs, config.eval_pairs, device)
            log(
                f"epoch {epoch + 1}: test rotation error median {record['test']['rotation_deg_median']:.3f} deg, "
                f"mean {record['test']['rotation_deg_mean']:.3f} deg (lower is better)"
            )
        if state["step_in_epoch"] >= steps_per_epoch:
            state["history"].append(record)
            state["epoch"] += 1
            state["step_in_epoch"] = 0
            state["epoch_losses"] = []
        else:
            state["partial"] = record
        state["seconds"] += time.monotonic() - last_ckpt
        last_ckpt = time.monotonic()
        checkpoint()

    model_path = export_torchscript(model, config.net, out / "model.pt", info={"protocol": config.protocol, "epochs_completed": state["epoch"]})
    card = {
        "model_file": model_path.name,
        "sha256": sha256_of(model_path),
        "config": config.to_dict(),
        "dataset": "ModelNet40 (official HDF5 layout), train split" + (f", first {config.limit_train} shapes" if config.limit_train else ""),
        "protocol": asdict(protocol),
        "epochs_completed": state["epoch"],
        "steps": state["global_step"],
        "history": state["history"] + ([state["partial"]] if "partial" in state and state["step_in_epoch"] else []),
        "initialised_from": init_record,
        "parameters": count_parameters(model),
        "torch_version": torch.__version__,
        "training_seconds": round(state["seconds"], 1),
        "device": str(device),
    }
    (out / "model_card.json").write_text(json.dumps(card, indent=2))
    log(f"wrote {model_path} and {out / 'model_card.json'}")
    return model_path
