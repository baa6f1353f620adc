"""Import Open3D once, quietly, with a clear message when a system library is missing."""

from __future__ import annotations

from .errors import O3dsoftError

try:
    import open3d
except OSError as e:  # pragma: no cover - depends on the machine
    hint = ""
    if "libusb" in str(e):
        hint = " Open3D needs the system library libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)."
    raise O3dsoftError(f"cannot import open3d: {e}.{hint}") from None

# Open3D prints its own warnings to stdout (e.g. "Read PLY failed"); o3dsoft reports errors itself.
open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Error)
