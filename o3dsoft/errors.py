"""Exceptions raised by o3dsoft.

Every error a user can cause (a bad file, a degenerate cloud, a wrong option) is an
:class:`O3dsoftError` whose message names the thing at fault and what was expected, so that the
CLI can print it as it is, without a traceback.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator


class O3dsoftError(Exception):
    """Base class of the errors o3dsoft raises on bad input; the CLI exits 1 on these."""

    exit_code = 1


class InputError(O3dsoftError, ValueError):
    """The content of an input (a point cloud, a transform, a weights file) is unusable."""


class UsageError(O3dsoftError, ValueError):
    """The input cannot even be opened as asked (unknown extension, missing file); CLI exit 2."""

    exit_code = 2


def first_line(error: BaseException) -> str:
    """The first line of an exception's message (libraries' messages often carry C++ traces), or
    the exception's type name when it has none: for one-line errors naming what failed."""
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM (``kill``, a scheduler's time limit) stops the work as Ctrl-C
    does, so that the same clean-up runs (no temporary file left, partial results summarised).
    A command started in the background by a shell (``cmd &``) ignores SIGINT, so ``kill`` is how
    it is stopped there. Only the main thread may set signal handlers; elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)
