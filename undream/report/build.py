"""Build a report: read and draw everything in memory, then write the folder atomically.

Nothing is written before every run is read and every picture drawn; the
folder is written as a temporary sibling and renamed into place, so ``out``
holds the old report or the new one, never half of one. ``out`` is refused
when it exists and is not a report (:data:`MARKER` says so), and a report
is replaced only with ``force``.
"""
from __future__ import annotations

import datetime as dt
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from undream.errors import SpecError
from undream.spec.io import naming
from undream.report import charts, page, tables
from undream.report.compare import cell_rows, compare
from undream.report.data import RunData, load_run
from undream.report.seen import SeenFinder
from undream.report.sheet import frame_files
from undream.report.transfer import Evaluation, csv_rows, transfer_rows

if TYPE_CHECKING:
    from undream.store import RunSnapshot, Store, SweepSnapshot

MARKER = "report.json"
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


@dataclass(frozen=True)
class Target:
    """What to report: one run (``folder``: its `undream run` output folder, if that is how it was
    named; ``evaluations``: what `undream evaluate` measured of its texture elsewhere) or one sweep,
    with the store that holds it."""

    store: "Store"
    run: "RunSnapshot | None" = None
    sweep: "SweepSnapshot | None" = None
    folder: Path | None = None
    evaluations: tuple[Evaluation, ...] = ()  # `undream evaluate --json` files shown beside a run's numbers


def is_report(folder: Path) -> bool:
    try:
        return "undream_report" in json.loads((folder / MARKER).read_text())
    except (OSError, ValueError, TypeError):
        return False


def check_out(out: Path, force: bool) -> None:
    """Refuse ``out`` when writing it could destroy something that is not a report (one line)."""
    if out.exists() and not out.is_dir():
        raise SpecError(f"--out {out}: is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not is_report(out):
            raise SpecError(f"--out {out}: exists and is not a report of `undream report` (no {MARKER}); "
                            "give a new folder")
        if not force:
            raise SpecError(f"--out {out}: holds a report already; give --force to replace it")
    parent = out.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise SpecError(f"--out {out}: {parent} is not a writable folder")


def run_files(data: RunData, command: str, back: str | None = None,
              evaluations: tuple[Evaluation, ...] = ()) -> dict[str, bytes]:
    """A run's report files (relative path → bytes): its page, pictures and tables; with
    ``evaluations``, the transfer table (``transfer.csv``)."""
    headline = tables.headline_rows(data.results)
    unseen = charts.unseen_sentence(data)
    conditions = tables.condition_rows(data.results)
    moved = transfer_rows(data.results, data.run.config, list(evaluations)) if evaluations else []
    body = page.run_body(data, headline, unseen, command, conditions, moved)
    if back is not None:
        body = f'<p class=meta><a href="{back}">← the sweep</a></p>' + body
    return {
        "index.html": page.document(f"undream report: {data.run.name}", body).encode(),
        **frame_files(data),
        "loss.png": charts.loss_png(data, command),
        "texture.png": charts.texture_png(data, command),
        "headline.csv": tables.to_csv(headline).encode(),
        "frames.csv": tables.to_csv(tables.frame_rows(data)).encode(),
        **({"conditions.csv": tables.to_csv(conditions).encode()} if conditions else {}),
        **({"transfer.csv": tables.to_csv(csv_rows(moved)).encode(),
            "transfer.png": charts.transfer_png(moved, command)} if moved else {}),
    }


def run_dir(run: "RunSnapshot") -> str:
    """The folder of a sweep's run inside the report: its name when that is a safe file name."""
    return f"runs/{run.name if SAFE_NAME.match(run.name) else run.id}"


def sweep_files(sweep: "SweepSnapshot", runs: list["RunSnapshot"], load: Callable[["RunSnapshot"], RunData],
                command: str) -> dict[str, bytes]:
    """A sweep's report files: its page, results.csv, the runs side by side (a chart per metric,
    comparison.csv), one folder per finished run (``load``: its data, read one run at a time and
    dropped once drawn, so that a sweep of many runs holds one run's frames at a time)."""
    rows = tables.sweep_rows(sweep, runs)
    side = compare(sweep, runs)
    files = {"results.csv": tables.to_csv(rows).encode(),
             "comparison.csv": tables.to_csv(cell_rows(side)).encode(),
             **{f"compare_{metric}.png": charts.compare_png(side, metric, command) for metric in side.cells}}
    links = {}
    for run, row in zip(runs, rows):
        if run.status == "done":
            folder = run_dir(run)
            links[row["run"]] = f"{folder}/index.html"
            files.update({f"{folder}/{name}": data
                          for name, data in run_files(load(run), command, "../../index.html").items()})
    files["index.html"] = page.document(f"undream report: sweep {sweep.name}",
                                        page.sweep_body(sweep, rows, side, links, command)).encode()
    return files


def _load(target: Target, work: Path, command: str) -> dict[str, bytes]:
    """Every file of the report, in memory; scenes unpacked under ``work`` for visibility."""
    finder = SeenFinder(target.store, work)
    try:
        if target.run is not None:
            data = load_run(target.store, target.run, partial(finder, folder=target.folder))
            return run_files(data, command, evaluations=target.evaluations)
        if target.sweep is None:
            raise SpecError("report: give a run or a sweep")
        if target.evaluations:
            raise SpecError(f"--evaluation: shown beside one run's numbers; {target.sweep.name!r} is a sweep "
                            "(report one of its runs by id)")
        runs = target.store.runs(sweep_id=target.sweep.id)
        return sweep_files(target.sweep, runs, partial(load_run, target.store, seen_of=finder), command)
    finally:
        finder.close()


def _write(out: Path, files: dict[str, bytes], marker: dict[str, Any]) -> None:
    out.absolute().parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.absolute().parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp's 0700 is for the temporary name only
    old = tmp.with_name(tmp.name.replace(".tmp-", ".old-"))
    try:
        for rel, data in files.items():  # a full disk names the file as the report would hold it
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            with naming(out / rel):
                (tmp / rel).write_bytes(data)
        with naming(out / MARKER):
            (tmp / MARKER).write_text(json.dumps(marker, indent=1) + "\n")
        if out.exists():
            os.rename(out, old)
        os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)


def build_report(target: Target, out: Path, force: bool, command: str) -> Path:
    """Write the report of ``target`` to ``out`` (see the module docstring); returns ``out/index.html``.

    ``command``: the command line that made it, written under every chart.
    """
    check_out(out, force)
    with tempfile.TemporaryDirectory(prefix="undream-report-") as work:
        files = _load(target, Path(work), command)
    what = target.run or target.sweep
    marker = {"undream_report": 1, "kind": "run" if target.run else "sweep", "id": what.id,  # type: ignore[union-attr]
              "name": what.name, "command": command,  # type: ignore[union-attr]
              "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")}
    _write(out, files, marker)
    return out / "index.html"
