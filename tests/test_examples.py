"""The examples and the README's demo run as a user would run them, with the shipped model."""

import json
import subprocess
import sys

import pytest
from click.testing import CliRunner

from o3dsoft.cli.main import main
from o3dsoft.coarse import default_weights_path, load_model, sha256_of
from o3dsoft.model import NetConfig

from .conftest import EXAMPLES, REPO


def test_shipped_weights_load_and_card_matches():
    path = default_weights_path()
    model = load_model()
    card = json.loads(path.with_suffix(".json").read_text())
    assert card["sha256"] == sha256_of(path)
    assert model.config == NetConfig.from_dict(card["config"]["net"])  # a card may predate later settings


def test_readme_demo_pair_errors_against_ground_truth():
    r = CliRunner().invoke(
        main, ["register", str(EXAMPLES / "bun045.ply"), str(EXAMPLES / "bun000.ply"), "--gt", str(EXAMPLES / "bun045_to_bun000.txt"), "--json"]
    )
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


def _scan_errors(*args):
    r = subprocess.run([sys.executable, str(REPO / "examples" / "register_scans.py"), *map(str, args)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    lines = [l.split() for l in r.stdout.splitlines() if l.strip().startswith("error against the ground truth")]
    return [(float(l[6]), float(l[9])) for l in lines], r.stdout


def test_scan_example_aligns_the_bundled_scans():
    errors, _ = _scan_errors(EXAMPLES / "bun045.ply", EXAMPLES / "bun000.ply", "--gt", EXAMPLES / "bun045_to_bun000.txt")
    assert len(errors) == 1 and errors[0][0] < 1.0 and errors[0][1] < 0.002  # 1 degree, 2 mm


def test_scan_example_runs_on_the_shared_laser_scans(real_scans_root, tmp_path):
    errors, out = _scan_errors(real_scans_root / "outdoor_laser_car", "--render", tmp_path)
    assert len(errors) == 1 and errors[0][0] < 1.0 and errors[0][1] < 0.3  # LiDAR's fine test: 1 degree, 30 cm
    assert "point-to-plane" in out and len(list(tmp_path.glob("*.png"))) == 1


def test_register_arrays_example_recovers_its_transform():
    r = subprocess.run([sys.executable, str(REPO / "examples" / "register_arrays.py")], capture_output=True, text=True, timeout=300)
    line = next(l for l in r.stdout.splitlines() if l.startswith("rotation error"))
    rot = float(line.split()[2])
    assert rot < 0.01


def test_multiway_sequence_example_corrects_the_odometry():
    r = subprocess.run([sys.executable, str(REPO / "examples" / "multiway_sequence.py")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = [l.split() for l in r.stdout.splitlines() if l.strip().startswith("view")]
    assert len(rows) == 6 and "6 of 6 views joined" in r.stdout
    for row in rows[1:]:  # "viewK: rotation A -> B deg, translation C -> D mm"
        odometry_deg, joined_deg, odometry_mm, joined_mm = float(row[2]), float(row[4]), float(row[7]), float(row[9])
        assert joined_deg < 1.0 and joined_mm < 2.0
        assert joined_deg < odometry_deg and joined_mm < odometry_mm


def test_odometry_example_follows_its_sensor():
    r = subprocess.run([sys.executable, str(REPO / "examples" / "odometry_lidar.py")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    steps = [l.split() for l in r.stdout.splitlines() if l.strip().startswith("sweep")]
    assert len(steps) == 14 and not any("(flagged)" in " ".join(row) for row in steps)
    for row in steps:  # "sweepK: A deg, B cm, confidence C"
        assert float(row[1]) < 0.2 and float(row[3]) < 5.0, row
    drift = r.stdout.split("the last sweep ends ")[1].split()
    assert float(drift[0]) < 10.0 and float(drift[3]) < 0.5  # cm and degrees over an 11 m path


def test_model_file_runs_with_torch_alone(tmp_path):
    # No o3dsoft import in the child: the TorchScript file must carry everything it runs.
    code = (
        "import sys, torch; m = torch.jit.load(sys.argv[1]); m.eval(); "
        "x = torch.rand(1, 200, 3) * 2 - 1; R, t, w = m(x, x.flip(1)); "
        "assert R.shape == (1, 3, 3) and t.shape == (1, 3) and w.shape == (1, 200); "
        "assert not [k for k in sys.modules if k.split('.')[0] == 'o3dsoft']; print('ok')"
    )
    r = subprocess.run([sys.executable, "-c", code, str(default_weights_path())], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"
