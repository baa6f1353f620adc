"""A built wheel carries the CLI and the shipped model inside the o3dsoft namespace."""

import subprocess
import sys
import zipfile

from .conftest import REPO


def test_wheel_contents(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", str(REPO), "--no-deps", "--no-build-isolation", "-w", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    (wheel,) = tmp_path.glob("o3dsoft-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "o3dsoft/cli/main.py" in names and "o3dsoft/strategies/votes.py" in names
    assert "o3dsoft/weights/o3dsoft_default.pt" in names and "o3dsoft/weights/o3dsoft_default.json" in names
    assert "o3dsoft/py.typed" in names  # type checkers read the package's annotations
    assert not [n for n in names if n.split("/")[0] in ("cli", "weights", "tests", "benchmarks", "examples")]
    entry_points = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    assert "o3dsoft = o3dsoft.cli.main:main" in entry_points
