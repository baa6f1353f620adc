"""Import Open3D once, quietly, with a clear message when a system library is missing."""

from __future__ import annotations

import functools
from typing import Any, Callable, TypeVar

from .errors import O3dsoftError

try:
    import open3d
except OSError as e:  # pragma: no cover - depends on the machine
    hint = ""
    if "libusb" in str(e):
        hint = " Open3D needs the system library libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)."
    raise O3dsoftError(f"cannot import open3d: {e}.{hint}") from None

F = TypeVar("F", bound=Callable[..., Any])


def quiet() -> Any:
    """A context in which Open3D prints no warnings (to stdout, e.g. "Read PLY failed"): o3dsoft
    reports problems itself. The caller's level is back after it; o3dsoft never changes it for
    the process."""
    return open3d.utility.VerbosityContextManager(open3d.utility.VerbosityLevel.Error)


def quietly(function: F) -> F:
    """`function`, run in :func:`quiet`."""

    @functools.wraps(function)
    def run(*args: Any, **kwargs: Any) -> Any:
        with quiet():
            return function(*args, **kwargs)

    return run  # type: ignore[return-value]
