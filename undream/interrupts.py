"""Signals that end a command: raised where the main thread is, held back while the store writes.

The command line (:func:`undream.cli.errors.signals_end_commands`) makes SIGTERM and SIGHUP end a
command as Ctrl-C does, with an exception, so that every ``finally`` on the way out runs. Raised at
an arbitrary point, that exception has two failure modes:

- in the middle of a database transaction (inside SQLAlchemy, between its ``BEGIN`` and the block
  that would roll it back), it can leave a connection holding SQLite's write lock, and every
  cleanup write after it (the run marked failed, its lease given up) waits out the busy timeout;
- inside a ``__del__`` or a callback, Python reports the exception ("Exception ignored in ...") and
  drops it, and the command goes on as if no signal had come.

:func:`held` defers a signal that arrives during its block to the block's end (the store wraps each
transaction in it, the scene cache each Dr.Jit frozen function: raised while Dr.Jit records, the
exception became Dr.Jit's RuntimeError and the command exited 1), and :func:`check`, called between a run's jobs, raises again a stop whose first
exception was dropped.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Any, Iterator, NoReturn

_depth = 0  # how many held blocks the main thread is in
_deferred: int | None = None  # a signal that arrived inside a held block, not raised yet
_raised: int | None = None  # a signal already raised once (its exception may have been dropped)


def interrupt(signum: int, _frame: Any) -> None:
    """The handler :func:`undream.cli.errors.signals_end_commands` installs: raise now, or at the end of
    the held block the main thread is in."""
    global _deferred
    if _depth:
        _deferred = signum
        return
    _raise(signum)


def _raise(signum: int) -> NoReturn:
    global _raised
    _raised = signum
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def held() -> Iterator[None]:
    """Run the block whole: a signal that arrives during it is raised when it ends (in the main
    thread; other threads never run signal handlers, so their blocks hold nothing)."""
    global _depth, _deferred
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if not _depth and _deferred is not None:
            signum, _deferred = _deferred, None
            _raise(signum)


def check() -> None:
    """Raise the stop a signal asked for if it has not ended the command yet (its exception was raised
    inside a ``__del__`` or a callback that dropped it). Called where a long loop can stop cleanly."""
    if _depth:
        return
    signum = _raised if _deferred is None else _deferred
    if signum is not None:
        _raise(signum)


def reset() -> None:
    """Forget past signals (the command that received them has ended)."""
    global _deferred, _raised
    _deferred = _raised = None
