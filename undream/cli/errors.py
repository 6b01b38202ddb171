"""Errors mapped at the command-line edge: one line on stderr, exit status 2."""
from __future__ import annotations

import functools
import sys
from typing import Any, Callable

import click

from undream.errors import UndreamError

EXIT_BAD_INPUT = 2


def one_line_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Turn an :class:`UndreamError` raised by a command into one stderr line and exit 2."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UndreamError as err:
            click.echo(f"undream: error: {' '.join(str(err).split())}", err=True)
            sys.exit(EXIT_BAD_INPUT)
    return wrapper
