import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from o3dsoft.cli.main import main
from o3dsoft.coarse import load_model, sha256_of
from o3dsoft.data import PairDataset, get_protocol, load_pairs
from o3dsoft.errors import InputError, O3dsoftError, UsageError
from o3dsoft.model import NetConfig
from o3dsoft.train import TrainConfig, train

from .conftest import TINY, tetra_off


def _config(root, out, **kw):
    base = dict(data=str(root), protocol="paper", out=str(out), limit_train=40, eval_pairs=10, net=TINY, epochs=1, batch_size=4)
    base.update(kw)
    return TrainConfig(**base)


def test_train_exports_a_usable_model_and_card(modelnet_root, tmp_path):
    path = train(_config(modelnet_root, tmp_path, max_steps=3), log=lambda m: None)
    card = json.loads((tmp_path / "model_card.json").read_text())
    assert card["sha256"] == sha256_of(path)
    assert card["steps"] == 3 and card["parameters"] > 0
    assert card["history"][0]["test"]["pairs"] == 10
    assert json.loads((tmp_path / "config.json").read_text())["protocol"] == "paper"
    model = load_model(path)
    assert model.config.k == TINY.k


@pytest.mark.parametrize("extra", [{}, {"lr_schedule": "cosine", "grad_clip": 0.01}, {"protocol": "incongruent-mix"}])
def test_resume_continues_exactly(modelnet_root, tmp_path, extra):
    # 4 steps in one go == 2 steps, stop, resume for 2 more.
    train(_config(modelnet_root, tmp_path / "a", max_steps=4, eval_pairs=0, **extra), log=lambda m: None)
    train(_config(modelnet_root, tmp_path / "b", max_steps=2, eval_pairs=0, **extra), log=lambda m: None)
    train(_config(modelnet_root, tmp_path / "b", max_steps=4, eval_pairs=0, **extra), resume=True, log=lambda m: None)
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert a["state"]["global_step"] == b["state"]["global_step"] == 4
    for k, v in a["model"].items():
        assert torch.allclose(v.float(), b["model"][k].float(), atol=1e-6), k
    assert a["scheduler"]["_last_lr"] == b["scheduler"]["_last_lr"]


def test_a_learning_rate_given_on_resume_is_the_one_trained_with(modelnet_root, tmp_path):
    for name, lr in (("same", 1e-3), ("other", 0.05)):
        train(_config(modelnet_root, tmp_path / name, max_steps=2, eval_pairs=0, lr=1e-3, lr_schedule="cosine"), log=lambda m: None)
        train(_config(modelnet_root, tmp_path / name, max_steps=4, eval_pairs=0, lr=lr, lr_schedule="cosine"), resume=True, log=lambda m: None)
    same, other = (torch.load(tmp_path / name / "checkpoint.pt", weights_only=False) for name in ("same", "other"))
    assert other["scheduler"]["base_lrs"] == [0.05] and [g["lr"] for g in other["optimiser"]["param_groups"]] == other["scheduler"]["_last_lr"]
    assert other["scheduler"]["_last_lr"][0] == pytest.approx(50 * same["scheduler"]["_last_lr"][0], rel=0.02)  # the same cosine, 50 times higher
    assert any(not torch.equal(same["model"][k], other["model"][k]) for k in same["model"])  # trained at that rate
    assert json.loads((tmp_path / "other" / "config.json").read_text())["lr"] == 0.05


def test_ctrl_c_keeps_the_steps_done_and_resume_goes_on_exactly(modelnet_root, tmp_path, monkeypatch):
    import os
    import signal

    import o3dsoft.train as train_module

    train(_config(modelnet_root, tmp_path / "a", max_steps=4, eval_pairs=0), log=lambda m: None)
    loss, calls = train_module.registration_loss, []

    def interrupted_in_step_2(*args):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of a step
        return loss(*args)

    monkeypatch.setattr(train_module, "registration_loss", interrupted_in_step_2)
    logged = []
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        train(_config(modelnet_root, tmp_path / "b", max_steps=4, eval_pairs=0), log=logged.append)  # checkpoints every 5 minutes
    assert signal.getsignal(signal.SIGINT) is before
    assert torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)["state"]["global_step"] == 2  # the step under way ended
    assert any("interrupted: checkpoint after step 2" in line for line in logged)
    card = json.loads((tmp_path / "b" / "model_card.json").read_text())  # the model so far is usable at once
    assert card["steps"] == 2 and card["sha256"] == sha256_of(tmp_path / "b" / "model.pt")
    (record,) = card["history"]  # the epoch under way, as a stop by --max-steps records it
    assert record["epoch"] == 1 and record["steps"] == 2 and record["partial"] and record["train_loss"] > 0
    assert load_model(tmp_path / "b" / "model.pt").config.k == TINY.k
    monkeypatch.setattr(train_module, "registration_loss", loss)
    train(_config(modelnet_root, tmp_path / "b", max_steps=4, eval_pairs=0), resume=True, log=lambda m: None)
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    for k, v in a["model"].items():
        assert torch.allclose(v.float(), b["model"][k].float(), atol=1e-6), k


def test_cosine_schedule_ends_at_lr_min(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path, eval_pairs=0, limit_train=8, epochs=2, lr_schedule="cosine", lr_min=1e-5), log=lambda m: None)
    ckpt = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert ckpt["scheduler"]["_last_lr"][0] == pytest.approx(1e-5)
    TrainConfig(lr=1e-6).validate()  # lr_min only matters to the cosine schedule
    with pytest.raises(InputError, match="lr_min = 0.01 must be between 0 and lr"):
        TrainConfig(lr_schedule="cosine", lr_min=1e-2).validate()
    with pytest.raises(InputError, match="lr_schedule = .step. must be one of constant, cosine"):
        train(_config(modelnet_root, tmp_path / "x", lr_schedule="step"))


def test_init_from_a_checkpoint(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path / "a", max_steps=2, eval_pairs=0), log=lambda m: None)
    train(_config(modelnet_root, tmp_path / "b", max_steps=1, eval_pairs=0, init=str(tmp_path / "a" / "checkpoint.pt")), log=lambda m: None)
    card = json.loads((tmp_path / "b" / "model_card.json").read_text())
    assert card["initialised_from"]["steps"] == 2 and card["steps"] == 1
    # An exported model file starts a run too, and its card names it.
    train(_config(modelnet_root, tmp_path / "m", max_steps=1, eval_pairs=0, init=str(tmp_path / "a" / "model.pt")), log=lambda m: None)
    card = json.loads((tmp_path / "m" / "model_card.json").read_text())
    assert card["initialised_from"]["sha256"] == sha256_of(tmp_path / "a" / "model.pt")
    with pytest.raises(UsageError, match="no such checkpoint or model file"):
        train(_config(modelnet_root, tmp_path / "n", max_steps=1, init=str(tmp_path / "missing.pt")))
    with pytest.raises(UsageError, match="is a folder, not a checkpoint or model file"):
        train(_config(modelnet_root, tmp_path / "n", max_steps=1, init=str(tmp_path / "a")))
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(InputError, match="junk.pt"):
        train(_config(modelnet_root, tmp_path / "j", max_steps=1, init=str(tmp_path / "junk.pt")))
    other = NetConfig(k=4, radius=0.3, channels=(8, 8, 8, 8, 8))
    with pytest.raises(
        InputError,
        match="network settings differ from this run's: k 8 \\(this run: 4\\), channels \\[8, 16, 16, 16, 32\\] \\(this run: \\[8, 8, 8, 8, 8\\]\\)$",
    ):
        train(_config(modelnet_root, tmp_path / "c", max_steps=1, net=other, init=str(tmp_path / "a" / "checkpoint.pt")))


def test_resume_errors(modelnet_root, tmp_path):
    with pytest.raises(UsageError, match="no checkpoint to resume from"):
        train(_config(modelnet_root, tmp_path, max_steps=1), resume=True)
    (tmp_path / "checkpoint.pt").write_bytes(b"garbage")
    with pytest.raises(InputError, match="unreadable checkpoint"):
        train(_config(modelnet_root, tmp_path, max_steps=1), resume=True)
    train(_config(modelnet_root, tmp_path / "c", max_steps=1, eval_pairs=0), log=lambda m: None)
    with pytest.raises(InputError, match="different protocol"):
        train(_config(modelnet_root, tmp_path / "c", max_steps=2, protocol="dcp"), resume=True)


def test_train_cli_smoke(modelnet_root, tmp_path):
    def run(out, *more):
        quick = ["--max-steps", "1", "--limit-train", "4", "--batch-size", "2", "--eval-pairs", "0", "--epochs", "1"]
        r = CliRunner().invoke(main, ["train", "--data", str(modelnet_root), "--out", str(out), *quick, *more])
        assert r.exit_code == 0, r.output

    run(tmp_path)
    assert (tmp_path / "model.pt").is_file() and (tmp_path / "model_card.json").is_file()
    assert load_model(tmp_path / "model.pt").config.relative is False
    run(tmp_path / "rel", "--relative")
    assert load_model(tmp_path / "rel" / "model.pt").config.relative is True


def test_checkpoints_written_before_the_relative_setting_resume_and_initialise(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path / "a", max_steps=1, eval_pairs=0), log=lambda m: None)
    path = tmp_path / "a" / "checkpoint.pt"
    ckpt = torch.load(path, weights_only=False)
    del ckpt["config"]["net"]["relative"]
    torch.save(ckpt, path)
    train(_config(modelnet_root, tmp_path / "a", max_steps=2, eval_pairs=0), resume=True, log=lambda m: None)
    train(_config(modelnet_root, tmp_path / "b", max_steps=1, eval_pairs=0, init=str(path)), log=lambda m: None)
    # The relative first layer has the same parameters: it may start from absolute-layer weights.
    train(_config(modelnet_root, tmp_path / "c", max_steps=1, eval_pairs=0, init=str(path), net=replace(TINY, relative=True)), log=lambda m: None)
    assert load_model(tmp_path / "c" / "model.pt").config.relative is True


def test_train_cli_missing_data(tmp_path, monkeypatch):
    monkeypatch.delenv("O3DSOFT_DATA", raising=False)
    r = CliRunner().invoke(main, ["train", "--out", str(tmp_path / "o"), "--max-steps", "1"])
    assert r.exit_code == 2 and "O3DSOFT_DATA" in r.output and "Traceback" not in r.output  # usage, as a missing file
    r = CliRunner().invoke(main, ["train", "--protocol", "bogus"])
    assert r.exit_code == 2 and "unknown protocol 'bogus'" in r.output


def test_disk_full_while_checkpointing_keeps_the_last_good_checkpoint(modelnet_root, tmp_path, monkeypatch):
    import o3dsoft.train as train_module

    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), log=lambda m: None)
    before = (tmp_path / "checkpoint.pt").read_bytes()

    def full_disk(obj, path):
        with open(path, "wb") as f:
            f.write(b"PK\x03\x04 half a checkpoint")
        raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")

    monkeypatch.setattr(train_module.torch, "save", full_disk)
    with pytest.raises(O3dsoftError, match="could not write the checkpoint .*the previous checkpoint is unchanged"):
        train(_config(modelnet_root, tmp_path, max_steps=2, eval_pairs=0), resume=True, log=lambda m: None)
    assert (tmp_path / "checkpoint.pt").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt", "config.json", "config.yaml", "model.pt", "model_card.json"]
    # The first checkpoint of a run: nothing to resume, so the advice is to start again, which works.
    fresh = tmp_path / "fresh"
    with pytest.raises(O3dsoftError, match="no checkpoint was written; .* start the run again with --overwrite"):
        train(_config(modelnet_root, fresh, max_steps=1, eval_pairs=0), log=lambda m: None)
    monkeypatch.undo()
    train(_config(modelnet_root, fresh, max_steps=1, eval_pairs=0), overwrite=True, log=lambda m: None)
    assert (fresh / "model.pt").is_file()


def test_two_processes_under_torchrun_stay_identical(modelnet_root, tmp_path):
    import subprocess
    import sys

    config = tmp_path / "tiny.yaml"
    config.write_text(f"net:\n  k: {TINY.k}\n  radius: {TINY.radius}\n  channels: {list(TINY.channels)}\n")
    out = tmp_path / "ddp"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
        "-m",
        "o3dsoft.cli.main",
        "train",
        "--config",
        str(config),
        "--data",
        str(modelnet_root),
        "--out",
        str(out),
        "--limit-train",
        "16",
        "--batch-size",
        "2",
        "--max-steps",
        "3",
        "--eval-pairs",
        "2",
        "--epochs",
        "1",
    ]
    env = {**__import__("os").environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    card = json.loads((out / "model_card.json").read_text())
    assert card["world_size"] == 2 and card["replicas_identical"] is True and card["steps"] == 3
    assert r.stderr.count("wrote ") == 1  # only rank 0 writes and logs
    ckpt = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ckpt["world_size"] == 2


def test_a_mixture_draws_each_batch_from_one_protocol_repeatably():
    from o3dsoft.train import _batches

    order = list(range(100))
    batches = _batches(order, 0, 10, [0.5, 0.25, 0.25], seed=1, epoch=2)
    assert len(batches) == 10 and [k[0] for b in batches for k in b] == order
    assert all(len({part for _, part in b}) == 1 for b in batches)
    assert len({b[0][1] for b in batches}) > 1  # several protocols over the epoch
    # A run resumed at batch 4 sees the batches an uninterrupted one does from there.
    assert _batches(order[40:], 4, 10, [0.5, 0.25, 0.25], seed=1, epoch=2) == batches[4:]


@pytest.mark.parametrize("mixture", ["incongruent-mix", "incongruent-view-mix"])
def test_mixture_training_evaluates_on_its_evaluation_protocol(modelnet_root, tmp_path, mixture):
    train(_config(modelnet_root, tmp_path, protocol=mixture, max_steps=2, eval_pairs=4), log=lambda m: None)
    card = json.loads((tmp_path / "model_card.json").read_text())
    assert [p["name"] for p in card["protocol"]["mixture"]][:2] == ["wide45", "wide45-partial"]
    assert card["history"][0]["test"]["pairs"] == 4


def test_views_train_in_batches_of_one_size(modelnet_root, tmp_path):
    path = train(_config(modelnet_root, tmp_path, protocol="incongruent-wide-view", max_steps=2, eval_pairs=4), log=lambda m: None)
    assert path.is_file() and json.loads((tmp_path / "model_card.json").read_text())["history"][0]["test"]["pairs"] == 4


@pytest.mark.parametrize("loss, weight", [("point_loss", 10.0), ("match_loss", 1.0)])
def test_a_further_loss_changes_the_training_and_is_recorded(modelnet_root, tmp_path, loss, weight):
    plain = train(_config(modelnet_root, tmp_path / "plain", max_steps=2, eval_pairs=0, protocol="incongruent"), log=lambda m: None)
    added = train(_config(modelnet_root, tmp_path / "added", max_steps=2, eval_pairs=0, protocol="incongruent", **{loss: weight}), log=lambda m: None)
    cards = [json.loads((p.parent / "model_card.json").read_text()) for p in (plain, added)]
    assert [c["config"][loss] for c in cards] == [0.0, weight]
    losses = [c["history"][0]["train_loss"] for c in cards]
    assert np.isfinite(losses).all() and losses[1] > losses[0]  # the same first pairs, a further term
    with pytest.raises(InputError, match=loss):
        _config(modelnet_root, tmp_path / "bad", **{loss: -1.0}).validate()


def test_the_initial_temperature_replaces_the_initial_weights_tau(modelnet_root, tmp_path):
    first = train(_config(modelnet_root, tmp_path / "first", max_steps=1, eval_pairs=0), log=lambda m: None)
    tau_of = lambda run: math.exp(torch.load(run / "checkpoint.pt", weights_only=True)["model"]["log_tau"].item())  # noqa: E731
    again = _config(modelnet_root, tmp_path / "again", max_steps=1, eval_pairs=0, lr=1e-6, init=str(first.parent / "checkpoint.pt"), init_temperature=0.5)
    train(again, log=lambda m: None)
    assert tau_of(first.parent) > 1.0 and tau_of(tmp_path / "again") == pytest.approx(0.5, rel=1e-4)  # one step of lr 1e-6 moves it less
    with pytest.raises(InputError, match="init_temperature"):
        _config(modelnet_root, tmp_path / "bad", init_temperature=0.0).validate()


def test_temporaries_left_by_a_killed_checkpoint_write_are_removed(modelnet_root, tmp_path):
    tmp_path.mkdir(exist_ok=True)
    stale = [tmp_path / ".checkpoint.abc123.pt", tmp_path / ".model.x9.pt"]
    for p in stale:
        p.write_bytes(b"half a checkpoint")  # what kill -9 during torch.save leaves
    (tmp_path / ".keep.me.pt").write_bytes(b"not ours")
    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), log=lambda m: None)
    assert not any(p.exists() for p in stale) and (tmp_path / ".keep.me.pt").exists()


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda c: c.pop("optimiser"), "damaged or incompatible checkpoint \\(KeyError: 'optimiser'\\)"),
        (lambda c: c["state"].pop("global_step"), "state lacks global_step"),
        (lambda c: c.update(torch_rng=torch.zeros(3)), "damaged or incompatible checkpoint"),
        (
            lambda c: c["model"].update({k: v[:1] for k, v in c["model"].items() if v.dim() and len(v) > 1}),
            "damaged or incompatible checkpoint \\(RuntimeError",
        ),
        (
            lambda c: next(v for v in c["model"].values() if v.is_floating_point() and v.numel() > 1).view(-1).__setitem__(0, float("nan")),
            "hold NaN or infinite values",
        ),
    ],
)
def test_a_damaged_checkpoint_is_one_error_naming_it(modelnet_root, tmp_path, damage, message):
    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), log=lambda m: None)
    path = tmp_path / "checkpoint.pt"
    ckpt = torch.load(path, weights_only=True)
    damage(ckpt)
    torch.save(ckpt, path)
    with pytest.raises(InputError, match=message):
        train(_config(modelnet_root, tmp_path, max_steps=2, eval_pairs=0), resume=True, log=lambda m: None)


def test_training_data_with_nan_coordinates_is_refused_by_name(tmp_path):
    import h5py

    from o3dsoft.data import get_protocol, load_pairs

    points = np.random.default_rng(0).normal(size=(4, 32, 3)).astype(np.float32)
    points[2, 5, 1] = np.nan
    with h5py.File(tmp_path / "ply_data_train0.h5", "w") as h5:
        h5["data"], h5["label"] = points, np.zeros((4, 1), dtype=np.int64)
    (tmp_path / "shape_names.txt").write_text("thing\n")
    with pytest.raises(InputError, match="ply_data_train0.h5: shape 2 \\(of 1 such\\) has NaN or infinite coordinates"):
        load_pairs(tmp_path, "train", get_protocol("dcp"), 0)


class _Payload:
    """Pickles to a call that creates a file: what a crafted checkpoint would run on load."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_checkpoint_carrying_code_is_refused_without_running_it(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), log=lambda m: None)
    marker = tmp_path / "ran"
    ckpt = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    ckpt["state"]["payload"] = _Payload(marker)
    torch.save(ckpt, tmp_path / "checkpoint.pt")
    with pytest.raises(InputError, match="unreadable checkpoint"):
        train(_config(modelnet_root, tmp_path, max_steps=2, eval_pairs=0), resume=True, log=lambda m: None)
    with pytest.raises(InputError, match="unreadable checkpoint"):
        train(_config(modelnet_root, tmp_path / "b", max_steps=1, eval_pairs=0, init=str(tmp_path / "checkpoint.pt")), log=lambda m: None)
    assert not marker.exists()


def test_a_time_limit_ends_the_run_with_a_checkpoint_and_a_model(modelnet_root, tmp_path):
    lines = []
    path = train(_config(modelnet_root, tmp_path, max_minutes=1e-6, epochs=3, eval_pairs=0), log=lines.append)
    card = json.loads((tmp_path / "model_card.json").read_text())
    assert card["steps"] == 1 and path.is_file()  # the first step outlasts the limit
    assert any(line.startswith("stopped: max_minutes = 1e-06 of training in this call, after step 1") for line in lines)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)["state"]
    assert state["global_step"] == 1 and state["epoch"] == 0  # --resume goes on from here
    with pytest.raises(InputError, match="max_minutes"):
        _config(modelnet_root, tmp_path, max_minutes=0).validate()


def test_the_gpu_machines_path_trains_from_packed_data_from_the_source_tree_without_open3d(modelnet_root, tmp_path):
    """benchmarks/device_train.py from the source tree, on data packed by benchmarks.pack_modelnet,
    fine-tuning a shipped model, with neither Open3D, trimesh nor an installed o3dsoft (the lent GPU
    machine has none of them)."""
    import os
    import site
    import subprocess
    import sys
    from pathlib import Path

    import h5py

    from benchmarks.pack_modelnet import pack

    repo = Path(__file__).resolve().parents[1]
    packed = tmp_path / "packed"
    pack(modelnet_root, packed, test_shapes=4, train_shapes=16)
    with h5py.File(packed / "ply_data_train0.h5", "r") as h5:
        assert h5["data"].shape[0] == 16 and h5["data"].dtype == np.float16
    blocked = tmp_path / "blocked"
    for name in ("open3d", "trimesh"):
        (blocked / name).mkdir(parents=True)
        (blocked / name / "__init__.py").write_text(f"raise ImportError('{name} is not on this machine')\n")
    out = tmp_path / "run"
    # -S: no site processing, so no .pth file installs o3dsoft; the packages' folder comes by PYTHONPATH.
    python = [sys.executable, "-S"]
    cmd = python + [str(repo / "benchmarks" / "device_train.py"), "train", "--init", "default", "--data", str(packed)]
    cmd += ["--protocol", "incongruent-mix", "--batch-size", "2", "--max-steps", "2", "--eval-pairs", "2", "--epochs", "1", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(blocked), *site.getsitepackages()]), "OMP_NUM_THREADS": "1"}
    for module in ("open3d", "trimesh", "o3dsoft"):
        assert subprocess.run(python + ["-c", f"import {module}"], env=env, capture_output=True, cwd=tmp_path).returncode != 0, module
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    card = json.loads((out / "model_card.json").read_text())
    assert card["steps"] == 2 and (out / "model.pt").is_file() and (out / "checkpoint.pt").is_file()


def test_training_the_overlap_head_alone_keeps_the_rest_of_the_network_and_its_statistics(modelnet_root, tmp_path):
    first = train(_config(modelnet_root, tmp_path / "first", max_steps=1, eval_pairs=0, protocol="incongruent-crop"), log=lambda m: None)
    headed = replace(TINY, overlap=8)
    run = _config(
        modelnet_root,
        tmp_path / "head",
        max_steps=3,
        eval_pairs=4,
        protocol="incongruent-crop",
        net=headed,
        init=str(first.parent / "checkpoint.pt"),
        only_overlap=True,
        overlap_loss=1.0,
    )
    train(run, log=lambda m: None)
    before = torch.load(first.parent / "checkpoint.pt", weights_only=True)["model"]
    after = torch.load(tmp_path / "head" / "checkpoint.pt", weights_only=True)["model"]
    assert set(after) - set(before) and all(k.startswith("overlap.") for k in set(after) - set(before))
    assert all(torch.equal(before[k], after[k]) for k in before)  # weights and BatchNorm statistics
    assert load_model(tmp_path / "head" / "model.pt").config.overlap == 8
    card = json.loads((tmp_path / "head" / "model_card.json").read_text())
    head = sum(v.numel() for k, v in after.items() if k.startswith("overlap.") and v.is_floating_point())
    assert card["trained_parameters"] == head and card["parameters"] > head
    with pytest.raises(InputError, match="overlap_loss"):
        _config(modelnet_root, tmp_path / "bad", overlap_loss=1.0).validate()
    with pytest.raises(InputError, match="only_overlap"):
        _config(modelnet_root, tmp_path / "bad", only_overlap=True).validate()


@pytest.mark.parametrize("recipe", sorted((Path(__file__).resolve().parents[1] / "docs" / "experiments").glob("*.yaml")), ids=lambda p: p.name)
def test_every_recipe_in_the_docs_is_a_valid_training_config(recipe):
    from o3dsoft.train import settings_from

    config = settings_from({}, {}, recipe)
    assert config.protocol and config.epochs >= 1


def test_a_second_dataset_makes_its_share_of_the_batches(modelnet_root, tmp_path):
    from benchmarks.make_shapes import write
    from o3dsoft.train import _training_sources, _TrainingPairs

    shapes = tmp_path / "shapes"
    write(shapes, train=3, test=1, points=1024, seed=0)
    config = _config(modelnet_root, tmp_path / "run", protocol="incongruent-mix", extra_data=str(shapes), extra_share=0.25, max_steps=2, eval_pairs=4)
    first = load_pairs(str(modelnet_root), "train", get_protocol("incongruent"), 0)
    parts = _training_sources(config, first)
    own, extra = parts[:-1], parts[-1:]
    assert np.isclose(sum(p.weight for p in own), 0.75) and np.isclose(sum(p.weight for p in extra), 0.25)
    assert extra[0].protocol.name == "incongruent-far-view" and len(extra[0].shapes.points) == 3
    # Indices past the smaller dataset wrap around it.
    pairs = _TrainingPairs([PairDataset(p.shapes, p.protocol, seed=0) for p in parts])
    assert torch.equal(pairs[(3, len(parts) - 1)][0], pairs[(0, len(parts) - 1)][0])

    train(config, log=lambda m: None)
    card = json.loads((tmp_path / "run" / "model_card.json").read_text())
    mixture = card["protocol"]["mixture"]
    assert mixture[-1]["name"] == "incongruent-far-view" and mixture[-1]["shapes"] == 3
    assert "25 % of the batches" in card["dataset"] and card["config"]["extra_data"] == str(shapes)


def test_a_second_dataset_must_match_on_resume(modelnet_root, tmp_path):
    from benchmarks.make_shapes import write

    shapes = tmp_path / "shapes"
    write(shapes, train=2, test=1, points=1024, seed=0)
    train(_config(modelnet_root, tmp_path / "run", protocol="incongruent", extra_data=str(shapes), max_steps=1, eval_pairs=0), log=lambda m: None)
    again = _config(modelnet_root, tmp_path / "run", protocol="incongruent", extra_data=str(shapes), extra_share=0.3, max_steps=2, eval_pairs=0)
    with pytest.raises(InputError, match="extra_share"):
        train(again, resume=True, log=lambda m: None)
    with pytest.raises(InputError, match="extra_share"):
        _config(modelnet_root, tmp_path / "bad", extra_share=1.0).validate()
    with pytest.raises(InputError, match="second dataset.*4096"):
        train(_config(modelnet_root, tmp_path / "big", extra_data=str(shapes), extra_points_per_shape=4096, max_steps=1), log=lambda m: None)


def test_a_checkpoint_given_as_weights_is_named_for_what_it_is(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), log=lambda m: None)
    with pytest.raises(InputError, match="checkpoint.pt: a training checkpoint .* use the model.pt train exports beside it"):
        load_model(tmp_path / "checkpoint.pt")
    r = CliRunner().invoke(main, ["train", "--data", str(modelnet_root), "--seed", "-1", "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "Invalid value for '--seed'" in r.output


def test_a_new_run_does_not_replace_a_run_unasked(modelnet_root, tmp_path):
    quick = dict(max_steps=1, eval_pairs=0)
    train(_config(modelnet_root, tmp_path, **quick), log=lambda m: None)
    before = (tmp_path / "checkpoint.pt").read_bytes()
    with pytest.raises(UsageError, match=r"holds a training run \(checkpoint.pt, model.pt.*--resume.*--overwrite"):
        train(_config(modelnet_root, tmp_path, seed=1, **quick), log=lambda m: None)
    assert (tmp_path / "checkpoint.pt").read_bytes() == before
    # the run folder's own settings name it: started again from them, it is refused too
    r = CliRunner().invoke(main, ["train", "--config", str(tmp_path / "config.yaml"), "--max-steps", "2"])
    assert r.exit_code == 2 and "holds a training run" in r.output, r.output
    assert (tmp_path / "checkpoint.pt").read_bytes() == before
    (tmp_path / "model.pt").write_bytes(b"an earlier run's model")  # replaced or removed, never kept beside the new run
    train(_config(modelnet_root, tmp_path, seed=1, max_steps=1, eval_pairs=0), overwrite=True, log=lambda m: None)
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=False)["config"]["seed"] == 1
    assert load_model(tmp_path / "model.pt").config.k == TINY.k


def test_a_run_stopped_before_its_first_checkpoint_is_named_so(modelnet_root, tmp_path):
    """A second Ctrl-C while the first checkpoint was written leaves the run's settings alone:
    --resume says there is nothing to go on with and how to start again, a new run is not told to
    --resume, and --resume with no data given says so too (not that the data is missing)."""
    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), log=lambda m: None)
    for name in ("checkpoint.pt", "model.pt", "model_card.json"):
        (tmp_path / name).unlink()
    with pytest.raises(
        UsageError, match=r"checkpoint.pt: no checkpoint to resume from \(a run stopped before its first checkpoint: --overwrite starts it again\)"
    ):
        train(_config(modelnet_root, tmp_path, max_steps=1), resume=True)
    with pytest.raises(
        UsageError, match=r"holds the settings of a run stopped before its first checkpoint \(config.json, config.yaml\); --overwrite"
    ) as refused:
        train(_config(modelnet_root, tmp_path, max_steps=1), log=lambda m: None)
    assert "--resume" not in str(refused.value)
    r = CliRunner().invoke(main, ["train", "--out", str(tmp_path / "empty"), "--resume"])
    assert r.exit_code == 2 and "no checkpoint to resume from" in r.output and "data" not in r.output, r.output


def test_a_run_resumes_with_its_data_named_another_way_and_not_with_other_data(modelnet_root, tmp_path, monkeypatch):
    monkeypatch.delenv("O3DSOFT_DATA", raising=False)
    monkeypatch.chdir(modelnet_root.parent)
    train(_config(modelnet_root, tmp_path / "r", data=modelnet_root.name, max_steps=1, eval_pairs=0), log=lambda m: None)  # a relative path
    monkeypatch.chdir(tmp_path)
    train(_config(modelnet_root, tmp_path / "r", data=str(modelnet_root) + "/", max_steps=2, eval_pairs=0), resume=True, log=lambda m: None)
    monkeypatch.setenv("O3DSOFT_DATA", str(modelnet_root))
    train(_config(modelnet_root, tmp_path / "e", data=None, max_steps=1, eval_pairs=0), log=lambda m: None)
    card = json.loads((tmp_path / "e" / "model_card.json").read_text())
    assert str(modelnet_root) in card["dataset"]  # the data the environment named
    (tmp_path / "other").mkdir()
    monkeypatch.setenv("O3DSOFT_DATA", str(tmp_path / "other"))
    with pytest.raises(InputError, match="different data"):
        train(_config(modelnet_root, tmp_path / "e", data=None, max_steps=2, eval_pairs=0), resume=True, log=lambda m: None)


def test_a_run_goes_on_from_its_data_copied_elsewhere(tmp_path):
    """A run trained on a lent machine comes back with its data at another path."""
    import shutil

    for category in ("box", "cone"):
        for i in range(4):
            folder = tmp_path / "there" / category / "train"
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"{category}_{i:04d}.off").write_text(tetra_off(i))
    quick = dict(limit_train=None, eval_pairs=0, batch_size=2, points_per_shape=64)
    train(_config(tmp_path / "there", tmp_path / "run", max_steps=1, **quick), log=lambda m: None)
    shutil.copytree(tmp_path / "there", tmp_path / "here")
    train(_config(tmp_path / "here", tmp_path / "run", max_steps=2, **quick), resume=True, log=lambda m: None)
    (tmp_path / "here" / "box" / "train" / "box_0003.off").rename(tmp_path / "here" / "box" / "train" / "box_0004.off")  # other shapes
    with pytest.raises(InputError, match="different data"):
        train(_config(tmp_path / "here", tmp_path / "run", max_steps=3, **quick), resume=True, log=lambda m: None)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without a CUDA GPU")
@pytest.mark.parametrize("device, message", [("cuda", "sees no CUDA GPU"), ("gpu", "invalid device 'gpu': expected cpu, cuda")])
def test_train_on_a_device_the_machine_lacks_is_one_line(modelnet_root, tmp_path, device, message):
    r = CliRunner().invoke(main, ["train", "--data", str(modelnet_root), "--out", str(tmp_path), "--max-steps", "1", "--device", device])
    assert r.exit_code == 2 and message in r.output and "report it" not in r.output, r.output
    assert not any(tmp_path.iterdir())


def test_resuming_a_finished_run_says_there_is_nothing_to_train(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path, max_steps=2, eval_pairs=0), log=lambda m: None)
    files = {name: (tmp_path / name).read_bytes() for name in ("config.yaml", "config.json", "model.pt", "model_card.json", "checkpoint.pt")}
    said = []
    train(_config(modelnet_root, tmp_path, max_steps=1, eval_pairs=0), resume=True, log=said.append)
    assert any("already reached max_steps = 1" in line and "its files are left as they are" in line for line in said), said
    assert not any("resumed at" in line for line in said), said  # not "resumed at epoch 1" before "nothing to train"
    # The run's settings still say how its model was trained (max_steps 2, not this call's 1).
    assert {name: (tmp_path / name).read_bytes() for name in files} == files
    # An export cut short after the last checkpoint (a card of another step) is made again.
    card = json.loads(files["model_card.json"])
    (tmp_path / "model_card.json").write_text(json.dumps({**card, "steps": 1}))
    said.clear()
    train(_config(modelnet_root, tmp_path, max_steps=2, eval_pairs=0), resume=True, log=said.append)
    assert any("its model is exported" in line for line in said), said
    assert json.loads((tmp_path / "model_card.json").read_text())["steps"] == 2
    said.clear()
    train(_config(modelnet_root, tmp_path, max_steps=3, eval_pairs=0), resume=True, log=said.append)
    assert any("resumed at epoch 1, step 2" in line for line in said), said


def test_a_card_marks_the_epoch_a_step_limit_cut_short(modelnet_root, tmp_path):
    train(_config(modelnet_root, tmp_path, max_steps=2, eval_pairs=4), log=lambda m: None)
    card = json.loads((tmp_path / "model_card.json").read_text())
    assert card["epochs_completed"] == 0 and card["steps"] == 2
    assert [(h["epoch"], h["steps"], h.get("partial")) for h in card["history"]] == [(1, 2, True)]
