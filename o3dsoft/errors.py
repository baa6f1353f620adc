"""Exceptions raised by o3dsoft.

Every error a user can cause (a bad file, a degenerate cloud, a wrong option) is an
:class:`O3dsoftError` whose message names the thing at fault and what was expected, so that the
CLI can print it as it is, without a traceback.
"""

from __future__ import annotations

import multiprocessing.context
import os
import signal
import sys
import threading
from contextlib import contextmanager
from typing import Callable, Iterator, Union


class O3dsoftError(Exception):
    """Base class of the errors o3dsoft raises on bad input; the CLI exits 1 on these."""

    exit_code = 1


class InputError(O3dsoftError, ValueError):
    """The content of an input (a point cloud, a transform, a weights file) is unusable."""


class UsageError(O3dsoftError, ValueError):
    """The input cannot even be opened as asked (unknown extension, missing file); CLI exit 2."""

    exit_code = 2


class UntrustedModelWarning(UserWarning):
    """A model file that is not one of the shipped models was loaded: it is a program."""


def caller_stacklevel() -> int:
    """The ``stacklevel`` of :func:`warnings.warn`, called in the function that calls this, that
    names the first line outside the o3dsoft package: the user's call, however deep the warning."""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame, level = sys._getframe(1), 1
    while frame.f_back is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    return level


def counted(n: int, noun: str) -> str:
    """ "1 pair", "3 pairs": a count and its noun, for messages."""
    return f"{n} {noun}" + ("" if n == 1 else "s")


class OutOfRange(InputError):
    """A setting out of its range; ``field`` names it (so that a config file's reader can add the
    line that gives it)."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


def refuse_out_of_range(settings: object, checks: "list[tuple[str, bool, str]]", kind: str) -> None:
    """Raise OutOfRange (an InputError) naming the first of `checks` ((field, in range, what it
    must be), in order) that fails, with the value `settings` holds: "{kind} setting k = 0 must be
    at least 1"."""
    for name, ok, expected in checks:
        if not ok:
            raise OutOfRange(f"{kind} setting {name} = {getattr(settings, name)!r} must be {expected}", name)


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
    it is stopped there. An error a library raises in place of the interrupt (Open3D's import
    stopped by Ctrl-C: "ImportError: initialization failed") leaves the block as the interrupt.
    Only the main thread may set signal handlers; elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    asked = []

    def interrupt(signum, frame):
        asked.append(signum)
        raise KeyboardInterrupt

    watched = [signal.SIGTERM]
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not where it is ignored or the caller's own
        watched.append(signal.SIGINT)
    before = {signum: signal.signal(signum, interrupt) for signum in watched}
    try:
        yield
    except Exception:
        if asked:
            raise KeyboardInterrupt from None
        raise
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)


@contextmanager
def _interrupt_held() -> Iterator[None]:
    """Ctrl-C (SIGINT) blocked in this thread within the block; one that arrives meanwhile is
    delivered at its end. A process started within inherits the block."""
    if not hasattr(signal, "pthread_sigmask"):  # Windows: a console's Ctrl-C is not inherited this way
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


class _HeldProcess(multiprocessing.context.SpawnProcess):
    """A spawned process that starts with Ctrl-C blocked (see :func:`spawn_context`)."""

    def start(self) -> None:
        with _interrupt_held():
            super().start()


class _HeldContext(multiprocessing.context.SpawnContext):
    Process = _HeldProcess


def spawn_context() -> multiprocessing.context.SpawnContext:
    """multiprocessing's "spawn" context, for worker pools, whose processes start with Ctrl-C
    blocked until they call :func:`release_interrupt`.

    A terminal sends Ctrl-C to every process of the command. A worker still importing torch or
    Open3D would print a traceback of its own; blocked, the signal waits until the worker is set
    up, and the parent, which gets it too, stops the pool."""
    return _HeldContext()


def _exit_quietly(signum, frame) -> None:
    os._exit(128 + signum)


def release_interrupt(handler: Union[Callable, int, None] = None) -> None:
    """In a worker of :func:`spawn_context`: Ctrl-C from now on goes to `handler` (default: the
    process ends at once, quietly: its parent reports the interrupt), or is ignored with
    ``signal.SIG_IGN``. One that arrived while blocked is delivered now."""
    signal.signal(signal.SIGINT, _exit_quietly if handler is None else handler)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
