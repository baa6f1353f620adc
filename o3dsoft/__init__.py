"""o3dsoft: rigid registration of 3D point clouds.

A learned soft-alignment network (TorchScript) estimates the pose, Open3D's ICP refines it
(point-to-point, or point-to-plane on scans), and a confidence says when not to trust it; where
it is not trusted, a global search takes over::

    import o3dsoft
    result = o3dsoft.register(source, target)      # (N, 3) arrays or Open3D point clouds
    result.transformation                           # (4, 4) T_target_source

Each stage is exposed on its own: :mod:`o3dsoft.preprocess` (clean, sample, normalise),
:mod:`o3dsoft.coarse` (the network), :mod:`o3dsoft.refine` (ICP, scoring), :mod:`o3dsoft.metrics`.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

from .errors import InputError, O3dsoftError, UntrustedModelWarning, UsageError

# The public names and the module of each, imported at first use: torch and Open3D take seconds
# to import, which `o3dsoft --help` and `--version` do not need.
_LAZY = {
    "CoarseModel": "coarse",
    "load_model": "coarse",
    "read_points": "io",
    "read_transform": "io",
    "read_poses": "io",
    "write_points": "io",
    "write_transform": "io",
    "pair_errors": "metrics",
    "rotation_error_deg": "metrics",
    "RegisterConfig": "config",
    "SearchConfig": "config",
    "FeatureSearchConfig": "config",
    "StartsConfig": "config",
    "VotesConfig": "config",
    "RestartConfig": "config",
    "ScreenConfig": "config",
    "SecondNetworkConfig": "config",
    "RegistrationResult": "pipeline",
    "register": "pipeline",
    "multiway": "multiway",
    "MultiwayConfig": "multiway",
    "MultiwayResult": "multiway",
    "odometry": "odometry",
    "OdometryConfig": "odometry",
    "OdometryResult": "odometry",
    "read_scans": "io",
    "ICPConfig": "refine",
    "ConfidenceConfig": "confidence",
    "DegeneracyConfig": "degeneracy",
    "FeatureMatchConfig": "search",
    "SymmetryConfig": "symmetry",
}

if TYPE_CHECKING:  # for type checkers and IDEs, which do not run __getattr__
    from .coarse import CoarseModel, load_model
    from .confidence import ConfidenceConfig
    from .config import FeatureSearchConfig, RegisterConfig, RestartConfig, ScreenConfig, SearchConfig, SecondNetworkConfig, StartsConfig, VotesConfig
    from .degeneracy import DegeneracyConfig
    from .io import read_points, read_poses, read_scans, read_transform, write_points, write_transform
    from .metrics import pair_errors, rotation_error_deg
    from .multiway import MultiwayConfig, MultiwayResult, multiway
    from .odometry import OdometryConfig, OdometryResult, odometry
    from .pipeline import RegistrationResult, register
    from .refine import ICPConfig
    from .search import FeatureMatchConfig
    from .symmetry import SymmetryConfig


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'o3dsoft' has no attribute {name!r}")


def __dir__() -> list:
    return sorted(list(globals()) + list(_LAZY))


try:
    __version__ = version("o3dsoft")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = [
    "CoarseModel",
    "ConfidenceConfig",
    "DegeneracyConfig",
    "FeatureMatchConfig",
    "FeatureSearchConfig",
    "ICPConfig",
    "InputError",
    "O3dsoftError",
    "RegisterConfig",
    "RegistrationResult",
    "RestartConfig",
    "ScreenConfig",
    "SearchConfig",
    "SecondNetworkConfig",
    "StartsConfig",
    "SymmetryConfig",
    "UntrustedModelWarning",
    "UsageError",
    "load_model",
    "multiway",
    "MultiwayConfig",
    "MultiwayResult",
    "odometry",
    "OdometryConfig",
    "OdometryResult",
    "read_scans",
    "pair_errors",
    "read_points",
    "read_poses",
    "read_transform",
    "register",
    "rotation_error_deg",
    "write_points",
    "write_transform",
    "VotesConfig",
    "__version__",
]
