"""Command-line options that several commands share, declared once."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import click

if TYPE_CHECKING:
    from undream.settings import LocalSettings

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


def local_settings(render: bool = True) -> "LocalSettings":
    """This process's settings, read from the environment here at the edge
    (:func:`undream.settings.load_local`: ``UNDREAM_MI_VARIANT``, ``UNDREAM_MEMORY_LIMIT``, ...).

    ``render``: the command renders, so Mitsuba's variant is chosen now, before anything renders
    (:func:`undream.variant.mitsuba`; later calls without a variant keep it), and Dr.Jit's pool is
    sized (``UNDREAM_DRJIT_THREADS``, at least two: :func:`undream.variant.set_drjit_pool`).
    """
    from undream.settings import load_local

    local = load_local()
    if render:
        from undream.variant import mitsuba, set_drjit_pool

        mitsuba(local.mi_variant, libcuda=local.libcuda_path, visible_devices=local.cuda_visible_devices)
        set_drjit_pool(local.drjit_threads)
    return local
