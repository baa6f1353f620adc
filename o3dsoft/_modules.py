"""Modules named after the function they hold (``o3dsoft.multiway``, ``o3dsoft.odometry``)."""

from __future__ import annotations

import sys
import types


class _CallableModule(types.ModuleType):
    """A module callable as its function of the same name: importing ``o3dsoft.X`` (for its
    config class) binds the package's ``X`` to the module, and ``o3dsoft.X(...)`` must still call
    the function."""

    def __call__(self, *args, **kwargs):
        return getattr(self, self.__name__.rsplit(".", 1)[-1])(*args, **kwargs)


def callable_as_its_function(module_name: str) -> None:
    """Make the module `module_name` (a ``__name__``) callable as its function of the same name."""
    sys.modules[module_name].__class__ = _CallableModule
