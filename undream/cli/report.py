"""``undream report TARGET --out DIR``: a run's or a sweep's results as an HTML page (:mod:`undream.report`).

TARGET is an ``undream run`` output folder (its own store), or a run id /
sweep id or name in the farm's store (the farm's settings). Everything is
read and drawn before DIR is written; bad input is one line on stderr, exit 2.
"""
from __future__ import annotations

import json
import shlex
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import click

from undream.cli.errors import one_line_errors
from undream.cli.farm import _run_store, _store, settings_options
from undream.cli.options import out_option
from undream.errors import SpecError, StoreError
from undream.redact import redact

if TYPE_CHECKING:
    from undream.report import Target
    from undream.settings import Settings
    from undream.store import Store

SETTINGS_FLAGS = (("settings_file", "--settings"), ("database", "--database"), ("blobs", "--blobs"))


def _folder_target(folder: Path, database: str | None = None) -> "Target":
    """The run an `undream run` output folder records, with its store (``database``: its URL where
    the folder keeps it without its password)."""
    from undream.report import Target

    try:
        meta = json.loads((folder / "metadata.json").read_text())
    except (OSError, ValueError):
        meta = None
    run_id = meta.get("run_id") if isinstance(meta, dict) else None
    if not (folder / "store").is_dir():
        hint = f"; give its run id {run_id} and the farm's settings" if run_id else ""
        raise SpecError(f"TARGET {folder}: not an output folder of `undream run` (no metadata.json and "
                        f"store/ in it){hint}")
    store = _run_store(folder, database)
    if run_id:
        return Target(store, run=store.get_run(str(run_id)), folder=folder)
    runs = store.runs()
    if not runs:
        raise SpecError(f"TARGET {folder}: its store holds no run")
    return Target(store, run=runs[-1], folder=folder)


def _store_target(store: "Store", ref: str, where: str) -> "Target":
    """Run ``ref`` (an id or its first characters), else sweep ``ref`` (an id or a name)."""
    from undream.report import Target

    try:
        return Target(store, run=store.find_run(ref))
    except StoreError as run_err:
        if "ambiguous" in str(run_err):
            raise StoreError(f"TARGET {ref!r}: {run_err}") from None
    try:
        return Target(store, sweep=store.find_sweep(ref))
    except StoreError:
        raise StoreError(f"TARGET {ref!r}: no such folder, and no run or sweep with that id or name in {where}") \
            from None


def _command(target: str, out: Path) -> str:
    """The command line as given (settings flags included, their secrets redacted), for the captions."""
    params = click.get_current_context().params
    flags = [part for name, flag in SETTINGS_FLAGS if params.get(name) is not None
             for part in (flag, str(redact(str(params[name]))))]
    measured = [part for path in params.get("evaluations") or () for part in ("--evaluation", str(path))]
    return shlex.join(["undream", "report", target, "--out", str(out), *measured, *flags])


@click.command("report")
@click.argument("target")
@out_option("Report folder to write: index.html, PNG charts and pictures, CSV tables.")
@click.option("--force", is_flag=True, help="Replace OUT when it holds an earlier report (never anything else).")
@click.option("--evaluation", "evaluations", multiple=True, type=click.Path(path_type=Path),
              help="A JSON file of `undream evaluate --json`: its transfer table beside the run's own numbers; "
                   "repeat for several.")
@settings_options
@one_line_errors
def report_cmd(target: str, out: Path, force: bool, evaluations: tuple[Path, ...],
               settings: Callable[..., "Settings"]) -> None:
    """Write the report of TARGET: an `undream run` output folder, or a run id or sweep id/name on the farm."""
    from undream.report import build_report
    from undream.report.transfer import load_evaluation
    from undream.store import mask_url

    command = _command(target, out)
    measured = tuple(load_evaluation(path) for path in evaluations)  # every file checked before any reading
    folder = Path(target)
    if folder.is_dir():
        found = _folder_target(folder, settings().database_url)
    elif folder.exists() or target.endswith(("/", ".json", ".yaml")):
        raise SpecError(f"TARGET {target}: not an output folder of `undream run`, a run id or a sweep")
    else:
        cfg = settings()
        where = mask_url(cfg.database_url) if cfg.database_url else f"the SQLite store in {cfg.blob_url}"
        found = _store_target(_store(cfg, create=False), target, where)
    page = build_report(replace(found, evaluations=measured), out, force, command)
    what: Any = found.run or found.sweep
    click.echo(f"wrote {page} ({'run' if found.run else 'sweep'} {what.name})")


COMMANDS = (report_cmd,)
