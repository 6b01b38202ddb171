"""Command-line options that several commands share, declared once."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import click

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]

force_option: Decorator = click.option("--force", is_flag=True, help="Replace OUT if it exists.")
check_option: Decorator = click.option(
    "--check", is_flag=True, help="Validate everything and print the memory and time estimate; write nothing.")
progress_option: Decorator = click.option("--progress/--no-progress", default=True,
                                          help="Show a progress bar.")
seed_option: Decorator = click.option("--seed", default=0, show_default=True,
                                      type=click.IntRange(0, 2**32 - 1))


def out_option(help: str) -> Decorator:
    """``--out OUT`` (required): the folder a command writes."""
    return click.option("--out", "out", required=True, type=click.Path(path_type=Path), help=help)


def spp_option(flag: str, default: int, help: str, most: int = 4096) -> Decorator:
    """A samples-per-pixel option ``flag`` in [1, most]."""
    return click.option(flag, default=default, show_default=True, type=click.IntRange(1, most), help=help)
