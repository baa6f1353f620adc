"""Import Open3D once, quietly, with a clear message when a system library is missing."""

from __future__ import annotations

import functools
import threading
from contextlib import contextmanager
from typing import Any, Callable, Iterator, TypeVar

from .errors import O3dsoftError

try:
    import open3d
except OSError as e:  # pragma: no cover - depends on the machine
    hint = ""
    if "libusb" in str(e):
        hint = " Open3D needs the system library libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)."
    raise O3dsoftError(f"cannot import open3d: {e}.{hint}") from None

F = TypeVar("F", bound=Callable[..., Any])


_LOCK = threading.Lock()
_QUIET = {"depth": 0, "level": None}  # blocks open across threads, and the level before the first


@contextmanager
def quiet() -> Iterator[None]:
    """A block in which Open3D prints no warnings (to stdout, e.g. "Read PLY failed"): o3dsoft
    reports problems itself. The caller's level is back once the last such block of any thread
    ends (Open3D's level is one for the process); o3dsoft never changes it for good."""
    with _LOCK:
        if _QUIET["depth"] == 0:
            _QUIET["level"] = open3d.utility.get_verbosity_level()
            open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
        _QUIET["depth"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _QUIET["depth"] -= 1
            if _QUIET["depth"] == 0:
                open3d.utility.set_verbosity_level(_QUIET["level"])


def quietly(function: F) -> F:
    """`function`, run in :func:`quiet`."""

    @functools.wraps(function)
    def run(*args: Any, **kwargs: Any) -> Any:
        with quiet():
            return function(*args, **kwargs)

    return run  # type: ignore[return-value]
