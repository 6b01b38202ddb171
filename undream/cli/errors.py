"""Errors mapped at the command-line edge: one line on stderr, exit status 2."""
from __future__ import annotations

import contextlib
import errno
import functools
import signal
import sys
import threading
from typing import Any, Callable, Iterator

import click

from undream import interrupts
from undream.errors import UndreamError
from undream.redact import install_log_redaction, redact_text

EXIT_BAD_INPUT = 2


def one_line_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Turn an :class:`UndreamError` raised by a command, or an ``OSError`` naming a file (a name
    too long, a full disk, no permission), into one stderr line and exit 2."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UndreamError as err:
            click.echo(f"undream: error: {redact_text(' '.join(str(err).split()))}", err=True)
            sys.exit(EXIT_BAD_INPUT)
        except OSError as err:  # the file system said no (a name too long, no space, no permission)
            if err.filename is None and err.errno in (errno.ENOSPC, errno.EDQUOT):  # a writer no one named
                click.echo(f"undream: error: {err.strerror}: a write failed (the system names no file)", err=True)
                sys.exit(EXIT_BAD_INPUT)
            if err.filename is None:
                raise
            where = err.filename if err.filename2 is None else f"{err.filename} → {err.filename2}"
            click.echo(redact_text(f"undream: error: {where}: {err.strerror or err}"), err=True)
            sys.exit(EXIT_BAD_INPUT)
    return wrapper


class OneLineGroup(click.Group):
    """The ``undream`` group: click's own errors (a bad option, a missing argument, a value out of
    range) are one stderr line and exit 2 too, instead of click's usage block."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        install_log_redaction()
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            with signals_end_commands():
                rv = super().main(*args, standalone_mode=False, **kwargs)
        except click.exceptions.Abort:
            click.echo("undream: aborted", err=True)
            sys.exit(1)
        except click.exceptions.NoArgsIsHelpError as err:  # `undream` alone: its help, as click shows it
            click.echo(err.ctx.get_help(), err=True)
            sys.exit(err.exit_code)
        except click.ClickException as err:
            click.echo(f"undream: error: {redact_text(_usage_line(err))}", err=True)
            sys.exit(err.exit_code)
        sys.exit(rv if isinstance(rv, int) and not isinstance(rv, bool) else 0)


@contextlib.contextmanager
def signals_end_commands() -> Iterator[None]:
    """While a command runs, SIGTERM and SIGHUP end it as Ctrl-C does: as an exception, so every
    ``finally`` and ``except BaseException`` on the way out runs (temporary folders removed, a run's
    lease given up and the run marked failed). The three are held back while the store writes and
    raised again if their first exception was dropped (:mod:`undream.interrupts`). Handlers set by
    others (Celery's) are left alone."""
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig, default in ((signal.SIGTERM, signal.SIG_DFL), (signal.SIGHUP, signal.SIG_DFL),
                             (signal.SIGINT, signal.default_int_handler)):
            if signal.getsignal(sig) in (default, None):
                previous[sig] = signal.signal(sig, interrupts.interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        interrupts.reset()


def _usage_line(err: click.ClickException) -> str:
    """``err``'s message on one line, with the command whose ``--help`` lists what is valid."""
    message = " ".join(err.format_message().split())
    ctx = getattr(err, "ctx", None)
    if isinstance(err, click.UsageError) and ctx is not None:
        return f"{ctx.command_path}: {message} (see {ctx.command_path} --help)"
    return message
