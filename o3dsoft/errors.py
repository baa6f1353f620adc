"""Exceptions raised by o3dsoft.

Every error a user can cause (a bad file, a degenerate cloud, a wrong option) is an
:class:`O3dsoftError` whose message names the thing at fault and what was expected, so that the
CLI can print it as it is, without a traceback.
"""

from __future__ import annotations


class O3dsoftError(Exception):
    """Base class of the errors o3dsoft raises on bad input; the CLI exits 1 on these."""

    exit_code = 1


class InputError(O3dsoftError, ValueError):
    """The content of an input (a point cloud, a transform, a weights file) is unusable."""


class UsageError(O3dsoftError, ValueError):
    """The input cannot even be opened as asked (unknown extension, missing file); CLI exit 2."""

    exit_code = 2
