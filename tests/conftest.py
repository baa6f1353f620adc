from __future__ import annotations

import os
from pathlib import Path
from typing import Tuple

import numpy as np
import pytest
import torch

from o3dsoft.coarse import export_torchscript
from o3dsoft.model import NetConfig, SoftAlignNet
from o3dsoft.transforms import apply_transform, euler_to_matrix

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("O3DSOFT_SHARED_DATA", REPO.parent / "shared" / "data"))
MODELNET = SHARED_DATA / "modelnet40_ply_hdf5_1024"
BUNNY = SHARED_DATA / "stanford_bunny"
REAL_SCANS = SHARED_DATA / "real_scans"
EXAMPLES = REPO / "examples" / "data"

TINY = NetConfig(k=8, radius=0.3, channels=(8, 16, 16, 16, 32))


@pytest.fixture(scope="session")
def modelnet_root() -> Path:
    if not (MODELNET / "shape_names.txt").is_file():
        pytest.skip(f"ModelNet40 not found at {MODELNET}")
    return MODELNET


@pytest.fixture(scope="session")
def bunny_root() -> Path:
    if not (BUNNY / "bun.conf").is_file():
        pytest.skip(f"Stanford Bunny scans not found at {BUNNY}")
    return BUNNY


@pytest.fixture(scope="session")
def real_scans_root() -> Path:
    if not (REAL_SCANS / "outdoor_laser_car" / "pairs.txt").is_file():
        pytest.skip(f"real scans not found at {REAL_SCANS}")
    return REAL_SCANS


@pytest.fixture(scope="session")
def tiny_model_path(tmp_path_factory) -> Path:
    """A small, untrained network exported to TorchScript (fast to load and run)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "tiny.pt"
    return export_torchscript(SoftAlignNet(TINY), TINY, path, info={"note": "untrained test model"})


def random_transform(rng: np.random.Generator, max_angle: float = 45.0, max_t: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix(rng.uniform(-max_angle, max_angle, size=3))
    T[:3, 3] = rng.uniform(-max_t, max_t, size=3)
    return T


apply = apply_transform


def blob(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """A non-symmetric random 3-D shape: an anisotropic Gaussian blob."""
    return rng.normal(size=(n, 3)) * np.array([1.0, 0.6, 0.3])


UTM = np.array([512_345.0, 4_123_456.0, 231.0])  # a georeferenced frame's offset, cloud units


def georeferenced_bunny(folder: Path, digits: int = 6) -> Tuple[Path, Path, Path]:
    """The example bunny pair moved UTM from its frame's origin, as `folder`'s bun045.ply and
    bun000.ply, with its truth in gt.txt written as published truths are: the rotation to
    `digits` decimals, the translation that rotation needs near the source (in full)."""
    from o3dsoft.io import read_points, read_transform, write_points

    S = np.eye(4)
    S[:3, 3] = UTM
    for name in ("bun045", "bun000"):
        write_points(folder / f"{name}.ply", read_points(EXAMPLES / f"{name}.ply") + UTM)
    T = S @ read_transform(EXAMPLES / "bun045_to_bun000.txt") @ np.linalg.inv(S)
    R = np.round(T[:3, :3], digits)
    T[:3, 3] += (T[:3, :3] - R) @ (read_points(EXAMPLES / "bun045.ply").mean(axis=0) + UTM)
    T[:3, :3] = R
    (folder / "gt.txt").write_text("\n".join(" ".join(f"{v:.10f}" for v in row) for row in T) + "\n")
    return folder / "bun045.ply", folder / "bun000.ply", folder / "gt.txt"


def python_output(code: str, timeout: float) -> str:
    """What a fresh Python process prints running `code` (the test fails, with its stderr, on a
    non-zero exit): for what must not touch the test process (forks, crashes, hangs)."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=timeout)
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    return run.stdout.decode()


def tetra_off(i: int, header: str = "OFF\n4 4 0\n") -> str:
    """An OFF file of a tetrahedron stretched to x = i + 2 (`header`: the first line(s), counts
    included), for ModelNet40-like folders of meshes (<category>/<split>/*.off)."""
    return header + f"0 0 0\n{i + 2} 0 0\n0 1 0\n0 0 1\n" + "3 0 1 2\n3 0 1 3\n3 0 2 3\n3 1 2 3\n"


def ring_sweep(T_world_sensor: np.ndarray, rng: np.random.Generator, elevations_deg=(-15.0, -10.0, -5.0, 0.0, 5.0)) -> np.ndarray:
    """(N, 3) a spinning LiDAR's sweep of rings at `elevations_deg` (0.5 degrees between rays, 1 cm
    range noise) in its own frame, ray-cast from pose T into a room: a floor 1.7 below, walls at
    x = +-20 and y = +-12, and a box's face at x = 6."""
    az, el = np.meshgrid(np.radians(np.arange(0, 360, 0.5)), np.radians(elevations_deg))
    rays = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    origin, world = T_world_sensor[:3, 3], rays @ T_world_sensor[:3, :3].T
    hit = np.full(len(rays), np.inf)
    for normal, offset in [((0, 0, 1), -1.7), ((1, 0, 0), 20), ((1, 0, 0), -20), ((0, 1, 0), 12), ((0, 1, 0), -12), ((1, 0, 0), 6)]:
        along = world @ np.asarray(normal, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):  # rays along a plane never meet it
            t = (offset - origin @ np.asarray(normal, dtype=float)) / along
            point = origin + t[:, None] * world
        ok = t > 0.5
        if offset == 6:  # the box: 4 m wide, 2.7 m high
            ok &= (np.abs(point[:, 1] - 3) < 2) & (point[:, 2] < 1.0)
        hit = np.where(ok & (t < hit), t, hit)
    seen = np.isfinite(hit)
    return rays[seen] * (hit[seen] + rng.normal(0.0, 0.01, seen.sum()))[:, None]
