import pytest
from click.testing import CliRunner

from o3dsoft.cli.main import main
from o3dsoft.configfile import read_config, write_config
from o3dsoft.errors import InputError, UsageError
from o3dsoft.model import NetConfig
from o3dsoft.train import TrainConfig, settings_from

from .conftest import REPO


def _yaml(tmp_path, text):
    path = tmp_path / "train.yaml"
    path.write_text(text)
    return path


def test_round_trip_of_a_full_config(tmp_path):
    config = TrainConfig(epochs=2, lr=5e-4, grad_clip=1.0, eval_pairs=None, net=NetConfig(k=8, channels=(8, 8, 8, 8, 16)))
    write_config(tmp_path / "c.yaml", config.to_dict())
    assert TrainConfig(**read_config(tmp_path / "c.yaml", TrainConfig)) == config


def test_values_are_checked_and_converted(tmp_path):
    settings = read_config(_yaml(tmp_path, "lr: 1\nlr_min: 1e-6\nnet:\n  channels: [4, 4, 4, 4, 8]\n"), TrainConfig)
    assert settings["lr"] == 1.0 and isinstance(settings["lr"], float) and settings["lr_min"] == 1e-6
    assert settings["net"] == NetConfig(channels=(4, 4, 4, 4, 8))
    assert read_config(_yaml(tmp_path, ""), TrainConfig) == {}


@pytest.mark.parametrize(
    "text, message",
    [
        ("epochs: 2\nbatch_sise: 4\n", r"train.yaml line 2: unknown key 'batch_sise' \(did you mean 'batch_size'\?\)"),
        ("epochs: five\n", r"line 1: 'epochs' must be an integer, got 'five'"),
        ("epochs: 2.5\n", r"'epochs' must be an integer, got 2.5"),
        ("lr: fast\n", r"'lr' must be a number"),
        ("net:\n  k: 8\n  radiu: 0.2\n", r"line 3: unknown key 'radiu' \(did you mean 'radius'\?\)"),
        ("lr: 0.01\nepochs: 2\nlr: 0.001\n", r"line 3: 'lr' is given twice \(first on line 1\)"),
        ("net:\n  k: 8\n  k: 16\n", r"line 3: 'k' is given twice \(first on line 2\)"),
        ("net:\n  shared_encoder: 1\n", r"'shared_encoder' must be true or false"),
        ("net: 3\n", r"line 1: expected a mapping of NetConfig settings"),
        ("epochs: 1\nnet:\n  k: 0\n", r"train.yaml line 3: net setting k = 0 must be at least 1"),  # the line of k itself
        ("net:\n  radius: -1\n", r"net setting radius = -1.0 must be positive"),
        ("net:\n  channels: []\n", r"net setting channels = \(\) must be a list of one or more positive widths"),
        ("net:\n  channels: [0, 8]\n", r"net setting channels = \(0, 8\)"),
        ("net:\n  overlap: -2\n", r"net setting overlap = -2 must be at least 0"),
        ("- epochs\n", r"expected a mapping of TrainConfig settings"),
        ("epochs: [1\n", r"train.yaml line 2: not valid YAML"),
        ('epochs: !!python/object/apply:os.system ["touch pwned"]\n', r"line 1: 'epochs': could not determine a constructor for the tag"),
    ],
)
def test_bad_config_files(tmp_path, text, message):
    with pytest.raises(InputError, match=message):
        read_config(_yaml(tmp_path, text), TrainConfig)


def test_missing_config_file(tmp_path):
    with pytest.raises(UsageError, match="no such config file"):
        read_config(tmp_path / "nope.yaml", TrainConfig)


def test_out_of_range_setting_is_named():
    with pytest.raises(InputError, match="epochs = 0 must be at least 1"):
        TrainConfig(epochs=0).validate()
    with pytest.raises(InputError, match="net setting overlap_layers = -1 must be at least 0"):
        TrainConfig(net=NetConfig(overlap_layers=-1)).validate()


def test_command_line_overrides_the_config_file(modelnet_root, tmp_path):
    config = _yaml(tmp_path, "epochs: 3\nbatch_size: 2\nlimit_train: 4\neval_pairs: 0\nnet:\n  k: 8\n  channels: [8, 8, 8, 8, 16]\n")
    out = tmp_path / "run"
    r = CliRunner().invoke(main, ["train", "--config", str(config), "--data", str(modelnet_root), "--out", str(out), "--epochs", "1", "--max-steps", "1"])
    assert r.exit_code == 0, r.output
    used = TrainConfig(**read_config(out / "config.yaml", TrainConfig))
    assert used.epochs == 1 and used.batch_size == 2 and used.net.k == 8 and used.max_steps == 1
    # --resume alone takes the run's own settings (here: batch 2, K 8), not the defaults.
    r = CliRunner().invoke(main, ["train", "--out", str(out), "--resume", "--max-steps", "2"])
    assert r.exit_code == 0, r.output
    resumed = TrainConfig(**read_config(out / "config.yaml", TrainConfig))
    assert resumed.batch_size == 2 and resumed.net.k == 8 and resumed.max_steps == 2
    r = CliRunner().invoke(main, ["train", "--config", str(_yaml(tmp_path, "epoch: 1\n"))])
    assert r.exit_code == 1 and "unknown key 'epoch'" in r.output and "Traceback" not in r.output
    # A network setting out of range: one line naming it, and no run folder left behind.
    bad = tmp_path / "bad"
    r = CliRunner().invoke(main, ["train", "--config", str(_yaml(tmp_path, "net:\n  k: 0\n")), "--data", str(modelnet_root), "--out", str(bad)])
    assert r.exit_code == 1 and "net setting k = 0 must be at least 1" in r.output and "Traceback" not in r.output
    assert not bad.exists()
    # A training setting out of range is named with the file's line, unless the command line gives it.
    ranged = _yaml(tmp_path, "batch_size: 2\nepochs: -3\n")
    r = CliRunner().invoke(main, ["train", "--config", str(ranged), "--data", str(modelnet_root), "--out", str(bad)])
    assert r.exit_code == 1 and "train.yaml line 2: training setting epochs = -3 must be at least 1" in r.output and not bad.exists(), r.output
    with pytest.raises(InputError, match="^training setting epochs = 0 must be at least 1$"):  # not the file's value: no line of it
        settings_from({"epochs": 0}, {}, ranged)


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "configs").glob("*.yaml")))
def test_shipped_configs_are_valid(name):
    config = TrainConfig(**read_config(REPO / "configs" / name, TrainConfig))
    config.validate()
    assert config.net == NetConfig(relative="relative" in name)
