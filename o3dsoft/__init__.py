"""o3dsoft: rigid registration of 3D point clouds.

A learned soft-alignment network (TorchScript) estimates the pose from any start inside its
training range; Open3D's point-to-point ICP refines it::

    import o3dsoft
    result = o3dsoft.register(source, target)      # (N, 3) arrays or Open3D point clouds
    result.transformation                           # (4, 4) T_target_source

Each stage is exposed on its own: :mod:`o3dsoft.preprocess` (clean, sample, normalise),
:mod:`o3dsoft.coarse` (the network), :mod:`o3dsoft.refine` (ICP, scoring), :mod:`o3dsoft.metrics`.
"""

from importlib.metadata import PackageNotFoundError, version

from .coarse import CoarseModel, load_model
from .errors import InputError, O3dsoftError, UsageError
from .io import read_points, read_transform, write_points, write_transform
from .metrics import pair_errors, rotation_error_deg
from .pipeline import RegisterConfig, RegistrationResult, register
from .refine import ICPConfig

try:
    __version__ = version("o3dsoft")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = [
    "CoarseModel",
    "ICPConfig",
    "InputError",
    "O3dsoftError",
    "RegisterConfig",
    "RegistrationResult",
    "UsageError",
    "load_model",
    "pair_errors",
    "read_points",
    "read_transform",
    "register",
    "rotation_error_deg",
    "write_points",
    "write_transform",
    "__version__",
]
