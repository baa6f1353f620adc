"""The examples and the README's demo run as a user would run them, with the shipped model."""

import json
import subprocess
import sys

import pytest
from click.testing import CliRunner

from o3dsoft.cli.main import main
from o3dsoft.coarse import default_weights_path, load_model, sha256_of

from .conftest import EXAMPLES, REPO


def test_shipped_weights_load_and_card_matches():
    path = default_weights_path()
    model = load_model()
    card = json.loads(path.with_suffix(".json").read_text())
    assert card["sha256"] == sha256_of(path)
    assert model.config.to_dict() == card["config"]["net"]


def test_readme_demo_pair_errors_against_ground_truth():
    r = CliRunner().invoke(main, ["register", str(EXAMPLES / "bun045.ply"), str(EXAMPLES / "bun000.ply"),
                                  "--gt", str(EXAMPLES / "bun045_to_bun000.txt"), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    # Real scans about 35 degrees apart with partial overlap: within 1 degree and 2 mm after ICP.
    assert out["errors"]["final"]["rotation_deg"] < 1.0
    assert out["errors"]["final"]["translation"] < 0.002
    assert out["fitness"] > 0.8


@pytest.mark.parametrize("script", ["register_pair.py", "register_arrays.py"])
def test_examples_run_without_arguments(script):
    r = subprocess.run([sys.executable, str(REPO / "examples" / script)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "rotation error" in r.stdout


def test_register_arrays_example_recovers_its_transform():
    r = subprocess.run([sys.executable, str(REPO / "examples" / "register_arrays.py")], capture_output=True, text=True, timeout=300)
    line = next(l for l in r.stdout.splitlines() if l.startswith("rotation error"))
    rot = float(line.split()[2])
    assert rot < 0.01
