"""Stand-in models and small pairs shared by the tests."""

from dataclasses import replace

import numpy as np

import o3dsoft
from o3dsoft.config import SecondNetworkConfig
from o3dsoft.metrics import rotation_error_deg

from .conftest import EXAMPLES, apply, blob, random_transform

# For tests of what follows a flagged first network (the search): no second network in between.
NO_SECOND = SecondNetworkConfig(weights=None)


def blob_pair(seed=0, n=400, max_angle=8.0, units=1.0):
    rng = np.random.default_rng(seed)
    src = blob(rng, n) * units
    T = random_transform(rng, max_angle=max_angle, max_t=0.2)
    T[:3, 3] *= units
    return src, apply(T, src), T


class StubModel:
    """A stand-in for CoarseModel: subclasses define run(source (B, N, 3), target (B, M, 3))."""

    def neighbours(self, points):
        return None

    def aligner(self, target):
        return lambda source, idx=None: self.run(source, target.expand(len(source), -1, -1))


class HalfwayModel(StubModel):
    """Stands in for a network: returns exactly half of the true rotation (points keep their order)."""

    def run(self, source, target):
        import torch
        from scipy.spatial.transform import Rotation

        s, t = source[0].double().numpy(), target[0].double().numpy()
        H = (s - s.mean(0)).T @ (t - t.mean(0))
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Rotation.from_rotvec(0.5 * Rotation.from_matrix(Vt.T @ D @ U.T).as_rotvec()).as_matrix()
        trans = t.mean(0) - R @ s.mean(0)
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float32)[None]  # noqa: E731
        return as_t(R), as_t(trans), torch.ones(1, len(s))


class NearSightedModel(StubModel):
    """Stands in for a network that finds the rotation left to do only when it is under 50 degrees
    (roughly like the trained one) and returns the identity otherwise. It knows the true rotation
    (rotations are the same in the normalised frame) and, in a batch of 24, that the sources come
    pre-rotated by the search's starts, in their order."""

    def __init__(self, R_true):
        from o3dsoft.model import NetConfig

        self.config = NetConfig(k=8)
        self.R_true = R_true
        self.batches = []

    def run(self, source, target):
        import torch

        from o3dsoft.search import cube_rotations

        self.batches.append(len(source))
        starts = cube_rotations() if len(source) == 24 else np.eye(3)[None]
        Rs, ts = [], []
        for h in range(len(source)):
            R = self.R_true @ starts[h].T  # what is left to do after the start
            if rotation_error_deg(R, np.eye(3)) > 50:
                R = np.eye(3)
            s, t = source[h].double().numpy(), target[h].double().numpy()
            Rs.append(R)
            ts.append(t.mean(0) - R @ s.mean(0))
        as_t = lambda a: torch.as_tensor(np.stack(a), dtype=torch.float32)  # noqa: E731
        return as_t(Rs), as_t(ts), torch.ones(len(source), source.shape[1])


class AlwaysWrongModel(StubModel):
    """Stands in for a network that returns the same wrong rotation R_wrong from every start of
    the search (it undoes the start, whose order it knows), the centroids put onto each other."""

    def __init__(self, R_wrong):
        from o3dsoft.model import NetConfig

        self.config = NetConfig(k=8)
        self.R_wrong = R_wrong
        self.batches = []

    def run(self, source, target):
        import torch

        from o3dsoft.search import cube_rotations

        self.batches.append(len(source))
        starts = cube_rotations() if len(source) == 24 else np.eye(3)[None]
        R = torch.as_tensor(self.R_wrong @ starts.transpose(0, 2, 1), dtype=torch.float32)
        t = target.mean(1) - torch.einsum("bij,bj->bi", R, source.mean(1))
        return R, t, torch.ones(len(source), source.shape[1])


class LocalModel(StubModel):
    """Stands in for the search network: from each of the 15 local starts (in their order) it
    returns the rotation left to do exactly."""

    def __init__(self, R_true, k=8):
        from o3dsoft.model import NetConfig

        self.config = NetConfig(k=k)
        self.R_true = R_true
        self.batches = []

    def run(self, source, target):
        import torch

        from o3dsoft.search import local_rotations

        self.batches.append(len(source))
        R = torch.as_tensor(self.R_true @ local_rotations().transpose(0, 2, 1), dtype=torch.float32)
        t = target.mean(1) - torch.einsum("bij,bj->bi", R, source.mean(1))
        return R, t, torch.ones(len(source), source.shape[1])


def bundled_scan_pair():
    src = o3dsoft.read_points(EXAMPLES / "bun045.ply")
    tgt = o3dsoft.read_points(EXAMPLES / "bun000.ply")
    return src, tgt, o3dsoft.read_transform(EXAMPLES / "bun045_to_bun000.txt")


def record_icp(monkeypatch) -> list:
    """Make every ICP run record (source size, distance schedule) in the list returned."""
    from o3dsoft import refine

    calls = []
    real_icp = refine.icp

    def recording_icp(source, target, init, distance, config=refine.ICPConfig(), target_normals=None, target_tree=None):
        calls.append((len(source), config.schedule))
        return real_icp(source, target, init, distance, config, target_normals, target_tree)

    monkeypatch.setattr(refine, "icp", recording_icp)
    return calls


def record_open3d_icp(monkeypatch) -> list:
    """Make every ICP stage (Open3D's point-to-point ICP, o3dsoft's point-to-plane steps) record
    (correspondence distance, relative_fitness criterion) in the list returned."""
    from o3dsoft import refine

    calls = []
    reg = refine.o3d.pipelines.registration
    real, real_plane = reg.registration_icp, refine.plane_steps

    def recording(source, target, distance, init, estimation, criteria):
        calls.append((distance, criteria.relative_fitness))
        return real(source, target, distance, init, estimation, criteria)

    def recording_plane(source, target, normals, init, distance, criteria, tree=None):
        calls.append((distance, criteria.relative_fitness))
        return real_plane(source, target, normals, init, distance, criteria, tree)

    monkeypatch.setattr(reg, "registration_icp", recording)
    monkeypatch.setattr(refine, "plane_steps", recording_plane)
    return calls


def moved_bunny(seed):
    src = o3dsoft.read_points(EXAMPLES / "bun000.ply")[::4]
    T = random_transform(np.random.default_rng(seed), 150.0, 0.1)
    return src, apply(T, src), T


def with_search(config, **parts):
    """`config` with some of its search settings replaced."""
    return replace(config, search=replace(config.search, **parts))
