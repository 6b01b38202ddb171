"""The farm's commands: ``submit``, ``worker``, ``status``, ``cancel``, ``resume``, ``sweep``, ``results``.

Registered on ``undream`` by :mod:`undream.cli`. Each builds one settings
object (defaults → ``--settings`` file → ``UNDREAM_*`` → flags) and passes it
down; the work is in :mod:`scheduler` and :mod:`workers`. Bad input and
unreachable services are one line on stderr, exit status 2.
"""
from __future__ import annotations

import csv
import functools
import io
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import click

from undream.cli.errors import one_line_errors
from undream.cli.options import check_option, local_settings
from undream.errors import SpecError, StoreError, UndreamError
from undream.redact import MASK, redact_text
from undream.runlist import MAX_PAGE, RUN_STATUSES

if TYPE_CHECKING:
    from celery import Celery

    from undream.settings import Settings
    from undream.store import Store

TABLE_ROWS = 100  # runs `undream results` shows in its table unless --limit says otherwise
EVENTS_SHOWN = 10  # a run's latest events `undream status RUN` shows (heals: scheduler.heal)


def settings_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``--settings FILE --broker URL --database URL --blobs URL``, turned into ``settings``."""
    @click.option("--settings", "settings_file", type=click.Path(path_type=Path), default=None,
                  help="Settings file (YAML; default $UNDREAM_SETTINGS).")
    @click.option("--broker", default=None, help="Broker URL (redis://host:6379/0; $UNDREAM_BROKER_URL).")
    @click.option("--database", default=None,
                  help="Run database URL (sqlite:///path or postgresql://...; $UNDREAM_DATABASE_URL).")
    @click.option("--blobs", default=None, help="Blob store of the farm: a shared folder, 'database' or s3://bucket/prefix "
                       "($UNDREAM_BLOB_URL).")
    @functools.wraps(fn)
    def wrapper(settings_file: Path | None, broker: str | None, database: str | None,
                blobs: str | None, **kwargs: Any) -> Any:
        from undream.settings import load_settings

        # The farm's commands and workers report in lines; no Hugging Face loading bars on stderr.
        os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
        kwargs["settings"] = lambda **more: load_settings(settings_file, broker_url=broker,
                                                          database_url=database, blob_url=blobs, **more)
        return fn(**kwargs)
    return wrapper


def _store(settings: "Settings", create: bool = True) -> "Store":
    """The farm's store; ``create`` False (commands that read, or change a recorded run): no
    database, folder or table is created, and none there is one line (exit 2)."""
    from undream.store import open_farm_store

    return open_farm_store(settings, create=create)


def _app(settings: "Settings") -> "Celery":
    """The Celery app, after checking that the broker and result backend answer."""
    from workers.app import check_reachable, create_celery_app

    app = create_celery_app(settings)
    check_reachable(app, settings)
    return app


def _dispatch(app: "Celery") -> Any:
    from workers.dispatch import CeleryDispatch

    return CeleryDispatch(app)


def _send(what: str, ref: str, fn: Callable[[], Any]) -> None:
    """Publish to the broker; a broker lost since the check is one line (runs stay recorded,
    queued until ``undream resume REF`` sends them)."""
    from workers.app import BrokerError

    try:
        fn()
    except BrokerError:
        raise
    except Exception as exc:  # kombu's OperationalError and the transport's own errors
        raise BrokerError(f"{what} recorded but not sent to the broker ({' '.join(str(exc).split())}); "
                          f"send it with `undream resume {ref}`") from None


def _table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "(none)"
    cols = list(rows[0])
    cells = [[_cell(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths)).rstrip()]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip() for row in cells]
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


@click.command("submit")
@click.argument("run_yaml", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), default=None,
              help="Output folder, reachable from the workers (default: <blobs>/outputs/<name>-<id>).")
@check_option
@settings_options
@one_line_errors
def submit_cmd(run_yaml: Path, out: Path | None, check: bool, settings: Callable[..., "Settings"]) -> None:
    """Validate RUN_YAML, then queue it on the farm; prints the run id (--check: validate only)."""
    from undream.spec.run import load_run_config

    cfg = settings()
    config = load_run_config(run_yaml)  # a malformed config is one line before the farm's modules load
    from scheduler.preflight import scene_sources
    from scheduler.submit import Validator, dispatch_starts, record

    if out is not None:
        _check_farm_out(out, scene_sources(config, run_yaml.parent), run_yaml, "undream submit")
    with tempfile.TemporaryDirectory(prefix="undream-submit-") as tmp:
        try:  # the run's own checks first: bad input is refused before the services are needed
            prepared = Validator(Path(tmp), local_settings())(config, run_yaml.parent)
        except StoreError:
            raise
        except UndreamError as err:
            raise SpecError(f"{run_yaml}: {err}") from None
        if check:
            click.echo(f"ok: {run_yaml} is valid; nothing written or queued")
            return
        app = _app(cfg)
        (run_id,) = record(_store(cfg), [prepared], cfg, out)
    _send(f"run {run_id}", run_id, lambda: dispatch_starts(_dispatch(app), [run_id]))
    click.echo(run_id)


@click.command("worker")
@click.option("--concurrency", type=click.IntRange(1, 1024), default=None,
              help="Worker processes (default 1; $UNDREAM_CONCURRENCY).")
@click.option("--threads", type=click.IntRange(1, 1024), default=None,
              help="Dr.Jit threads per process (default: the cores shared out; $UNDREAM_DRJIT_THREADS).")
@click.option("--loglevel", default="INFO", show_default=True,
              type=click.Choice(["DEBUG", "INFO", "WARNING", "ERROR"]))
@settings_options
@one_line_errors
def worker_cmd(concurrency: int | None, threads: int | None, loglevel: str,
               settings: Callable[..., "Settings"]) -> None:
    """Run a farm worker (a prefork Celery worker; Mitsuba only in its child processes)."""
    from workers.main import run_worker
    from workers.startup import wait_for_store

    cfg = settings(concurrency=concurrency, drjit_threads=threads)
    _app(cfg)
    # waited for, never another farm's; each worker process opens its own connections
    with wait_for_store(cfg, lambda line: click.echo(line, err=True)) as store:
        store.blobs.check_writable()  # else its runs' start would retry, give up and stay queued
    run_worker(cfg, loglevel)


@click.command("status")
@click.argument("run", required=False)
@click.option("--out", "out", type=click.Path(path_type=Path), default=None,
              help="An `undream run` output folder: show the run recorded in its store.")
@click.option("--limit", type=click.IntRange(1, MAX_PAGE), default=50, show_default=True,
              help="Show this many runs, newest first.")
@click.option("--all", "show_all", is_flag=True, help="Show every run (instead of --limit).")
@click.option("--state", type=click.Choice(RUN_STATUSES), default=None, help="Only runs in this state.")
@click.option("--sweep", default=None, help="Only the runs of this sweep (an id or a name).")
@settings_options
@one_line_errors
def status_cmd(run: str | None, out: Path | None, limit: int, show_all: bool, state: str | None,
               sweep: str | None, settings: Callable[..., "Settings"]) -> None:
    """The newest runs as a table, with every run counted by state; or RUN (an id or its first
    characters) with its current jobs.

    Runs whose process is gone (see `undream run`) are marked failed first, with the reason.
    """
    from scheduler.lease import expire_stale
    from scheduler.query import job_rows, run_rows

    if out is not None:
        _status_of_folder(out, run, state, sweep, click.get_current_context().params.get("database"),
                          settings().database_url)
        return
    store = _store(settings(), create=False)
    expire_stale(store)
    if run is None:
        sweep_id = store.find_sweep(sweep).id if sweep else None
        page = store.runs_page(state, sweep_id, None if show_all else limit)
        click.echo(_table(run_rows(store, page.runs)))
        click.echo(_tally(len(page.runs), page.total, store.status_counts(sweep_id), state))
        if out is None:
            _echo_stuck(store, settings())
        return
    _echo_run(store, store.find_run(run))


def _echo_run(store: "Store", snap: Any) -> None:
    """One run's row, error, current jobs and latest events."""
    from scheduler.query import job_rows, run_rows

    click.echo(_table(run_rows(store, [snap])))
    if snap.error:
        click.echo(f"error: {snap.error}")
    phase, k, rows = job_rows(store, snap)
    click.echo(f"\n{phase} jobs, k={k}:")
    click.echo(_table(rows))
    events = store.events(snap.id, limit=EVENTS_SHOWN)
    if events:
        click.echo("\nevents:")
        click.echo("\n".join(f"{e.time:%Y-%m-%d %H:%M:%S}  {e.by}  {e.line}" for e in events))


def _by_state(counts: dict[str, int]) -> str:
    """`` (3 queued, 2 done)``: runs counted by state, in the states' order; '' without runs."""
    states = ", ".join(f"{counts[s]} {s}" for s in RUN_STATUSES if counts.get(s))
    return f" ({states})" if states else ""


def _tally(shown: int, total: int, counts: dict[str, int], state: str | None) -> str:
    """The line under a runs table: how many it shows of how many, and every run counted by state."""
    line = f"\n{shown} of {total} run{'' if total == 1 else 's'}{f' {state}' if state else ''}, newest first"
    line += _by_state(counts)
    if shown < total:
        line += "; more with --limit N or --all, fewer with --state or --sweep"
    return line


def _echo_stuck(store: "Store", cfg: "Settings") -> None:
    """The runs that cannot make progress (:func:`workers.health.stuck_runs`), after the table."""
    from scheduler.heal import StallRule
    from workers.health import farm_view, probe, stuck_runs

    report = stuck_runs(store, lambda: probe(cfg), rule=StallRule.of(cfg), view=lambda: farm_view(cfg))
    if not report["asked"]:
        return
    if report["queues"] is None:
        live = f"unknown ({report['broker_error']})"
    else:
        live = "; ".join(f"{q}: {len(w)} worker(s)" for q, w in report["queues"].items()) or "none"
    click.echo(f"\nlive queues: {live}")
    rows = [{"run": r["run_id"][:8], "name": r["run"], "state": r["state"], "since": r["since"][11:19],
             "stalled": _duration(r["stalled_s"]), "reason": r["reason"] + (f" ({r['job']}, attempt {r['attempts']} of {r['max_attempts']}; "
                                      f"failures {r['failures']} of {r['failure_budget']})" if r["state"] == "failing" else "")}
            for r in report["waiting"] + report["failing"] + report["stalled"]]
    if not rows:
        click.echo("stuck: none" if report["n_waiting"] is not None else "stuck: none failing; waiting unknown")
        return
    stalled = f", {len(report['stalled'])} stalled" if report["stalled"] else ""
    click.echo(f"stuck: {_count(report['n_waiting'])} waiting, {report['n_failing']} failing{stalled}")
    click.echo(_table(rows))
    hidden = (report["n_waiting"] or 0) + report["n_failing"] + len(report["stalled"]) - len(rows)
    if hidden > 0:
        click.echo(f"… {hidden} more, stalled less long")


def _duration(seconds: float) -> str:
    """``seconds`` as 42s, 5m03s or 2h07m."""
    s = int(seconds)
    return f"{s}s" if s < 60 else f"{s // 60}m{s % 60:02d}s" if s < 3600 else f"{s // 3600}h{s // 60 % 60:02d}m"


def _count(n: int | None) -> str:
    return "unknown" if n is None else str(n)


def _run_store(out: Path, database: str | None = None) -> "Store":
    """The store of an `undream run` output folder: its database URL from the folder's metadata.json,
    or ``database`` (``--database``) where that URL's password was redacted there."""
    from scheduler.preflight import METADATA, is_run_output, run_store_url
    from undream.store import open_store

    if not is_run_output(out) or not (out / "store").is_dir():
        raise SpecError(f"--out {out}: not an output folder of `undream run` (no {METADATA} and store/)")
    url = run_store_url(out)
    if url and MASK in url:
        if not database:
            raise SpecError(f"--out {out}: the run's store URL is kept without its password ({url}); "
                            "give it with --database URL")
        url = database
    return open_store(url, out / "store", create=False)


def _status_of_folder(out: Path, run: str | None, state: str | None, sweep: str | None,
                      flag: str | None, database: str | None) -> None:
    """``undream status --out FOLDER``: the runs recorded for FOLDER in its store (a shared database
    holds other folders' runs too: they are not listed), or RUN among them. ``flag``: ``--database``
    as given, refused in one line when it is not the folder's database (another URL, or any URL for a
    folder whose store is its own SQLite file): another database's runs were listed as the folder's.
    ``database``: the settings' URL, used where the folder keeps its URL without its password."""
    from scheduler.lease import expire_stale
    from scheduler.preflight import run_store_url
    from scheduler.query import run_rows

    if sweep:
        raise SpecError(f"--sweep {sweep}: an `undream run` output folder holds no sweep; give --out or --sweep")
    url = run_store_url(out) if (out / "store").is_dir() else None
    if flag and (out / "store").is_dir() and redact_text(flag) != (url or ""):
        kept = url or f"its own SQLite file in {out / 'store'}"
        raise SpecError(f"--database {redact_text(flag)}: not the database of --out {out}'s run ({kept}); "
                        "give --out alone, or --database with that database's URL")
    store = _run_store(out, flag or database)
    expire_stale(store)
    mine = [r for r in store.runs() if r.out_dir and Path(r.out_dir).resolve() == out.resolve()]
    if not mine:
        raise SpecError(f"--out {out}: its store records no run of this folder")
    if run is not None:
        snap = next((r for r in mine if r.id.startswith(run) or r.name == run), None)
        if snap is None:
            raise SpecError(f"{run}: no run of --out {out} has this id or name ({', '.join(r.id[:8] for r in mine)})")
        _echo_run(store, snap)
        return
    shown = list(reversed([r for r in mine if state is None or r.status == state]))
    counts: dict[str, int] = {}
    for r in mine:
        counts[r.status] = counts.get(r.status, 0) + 1
    click.echo(_table(run_rows(store, shown)))
    click.echo(_tally(len(shown), len(shown), counts, state))


@click.command("cancel")
@click.argument("run")
@settings_options
@one_line_errors
def cancel_cmd(run: str, settings: Callable[..., "Settings"]) -> None:
    """Cancel RUN: its queued jobs and callbacks find it cancelled and do nothing."""
    from scheduler.stages import cancel

    store = _store(settings(), create=False)
    snap = store.find_run(run)
    if cancel(store, snap.id):
        click.echo(f"cancelled {snap.id}")
    else:
        click.echo(f"run {snap.id} is {store.get_run(snap.id).status}; nothing to cancel")


@click.command("resume")
@click.argument("run", metavar="RUN|SWEEP")
@settings_options
@one_line_errors
def resume_cmd(run: str, settings: Callable[..., "Settings"]) -> None:
    """Send RUN's current work to the farm again, from what the store says (after any crash).

    RUN may be a sweep (its id, the id's first characters, or its name): every run of it still
    queued has its start sent again (a start sent twice plans the run once), and every run of it
    running or evaluating its current work (after a restarted broker)."""
    from scheduler.lease import expire_stale
    from scheduler.stages import resume

    cfg = settings()
    app = _app(cfg)
    store = _store(cfg, create=False)
    try:
        snap = store.find_run(run)
    except StoreError as not_a_run:
        _resume_sweep(store, run, app, not_a_run)
        return
    expire_stale(store, [snap])
    owner = store.get_run(snap.id).owner
    if owner is not None:
        raise StoreError(f"run {snap.id}: being run by {owner}, which is alive; it needs no resume")
    phase: list[str] = []
    _send(f"run {snap.id}", snap.id, lambda: phase.append(resume(store, snap.id, _dispatch(app))))
    click.echo(f"run {snap.id} is done" if phase == ["done"] else f"resumed {snap.id}: {phase[0]}")


def _resume_sweep(store: "Store", ref: str, app: "Celery", not_a_run: StoreError) -> None:
    """``undream resume SWEEP``: the start of every queued run of the sweep sent again; no sweep
    ``ref`` either is the run's error (not found, or ambiguous), saying that no sweep matched."""
    from scheduler.stages import resume_sweep

    try:
        sweep = store.find_sweep(ref)
    except StoreError:
        raise StoreError(f"{not_a_run}; no sweep has that id or name either") from None
    sent: list[tuple[list[str], list[str]]] = []
    _send(f"sweep {sweep.id}", sweep.id, lambda: sent.append(resume_sweep(store, sweep.id, _dispatch(app))))
    (queued, active), = sent
    more = f", {len(active)} running run(s) resumed" if active else ""
    click.echo(f"resumed sweep {sweep.id}: {len(queued)} queued run(s) sent{more}")


@click.command("sweep")
@click.argument("sweep_yaml", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), default=None,
              help="Output folder; each run writes OUT/<run name> (default: under the blob folder).")
@click.option("--max-runs", type=click.IntRange(1, 10**7), default=None,
              help="Refuse a grid of more runs than this (default 10000).")
@check_option
@settings_options
@one_line_errors
def sweep_cmd(sweep_yaml: Path, out: Path | None, max_runs: int | None, check: bool,
              settings: Callable[..., "Settings"]) -> None:
    """Expand SWEEP_YAML's grid into runs, validate them all, then queue them; prints the sweep id
    (--check: validate only)."""
    from scheduler.sweep import load_sweep

    cfg = settings()
    sweep = load_sweep(sweep_yaml) if max_runs is None else load_sweep(sweep_yaml, max_runs)
    from scheduler.submit import dispatch_starts, record_sweep  # the farm's modules: after the sweep parsed

    if out is not None:
        from scheduler.preflight import scene_sources

        scenes = sorted({s for r in sweep.runs for s in scene_sources(r.config, r.base_dir)})
        _check_farm_out(out, scenes, sweep_yaml, "undream sweep")
    with tempfile.TemporaryDirectory(prefix="undream-sweep-") as tmp:
        prepared = _validate_sweep(sweep, sweep_yaml, Path(tmp))  # before the services are needed
        if check:
            click.echo(f"ok: {sweep_yaml} is valid: {len(sweep.runs)} runs; nothing written or queued")
            return
        app = _app(cfg)
        sweep_id, run_ids = record_sweep(_store(cfg), sweep, prepared, cfg, out)  # all or nothing
    click.echo(sweep_id)  # first: a sweep whose sending is interrupted is resumed by this id
    _send(f"sweep {sweep_id}", sweep_id, lambda: dispatch_starts(_dispatch(app), run_ids))
    click.echo(_table([{"run": r, "name": p.config.name, **s.values}
                       for r, p, s in zip(run_ids, prepared, sweep.runs)]))


def _check_farm_out(out: Path, scenes: list[Path], source: Path, command: str) -> None:
    """``--out`` of a run or sweep for the farm, checked when it is submitted (the output-folder rule
    of :func:`scheduler.preflight.check_output_folder`, without --force: absent or empty)."""
    from scheduler.preflight import check_output_folder

    for scene in scenes:
        check_output_folder(out, scene, force=False, command=command, inputs=(source,))


def _validate_sweep(sweep: Any, sweep_yaml: Path, tmp: Path) -> list[Any]:
    """Every run of ``sweep`` validated (:class:`scheduler.submit.Validator`, scenes prepared in ``tmp``);
    the first error names the sweep file and the run."""
    from scheduler.submit import Validator

    validate, prepared = Validator(tmp, local_settings()), []
    for i, run in enumerate(sweep.runs):
        try:
            prepared.append(validate(run.config, run.base_dir))
        except StoreError:
            raise
        except UndreamError as err:
            raise SpecError(f"{sweep_yaml}: run {i} ({run.config.name}): {err}") from None
    return prepared


@click.command("results")
@click.argument("sweep")
@click.option("--csv", "as_csv", is_flag=True, help="CSV of every run (or --limit runs) instead of a table.")
@click.option("--limit", type=click.IntRange(1, MAX_PAGE), default=None,
              help="Show this many runs, in grid order (default: 100 in the table, every run in --csv).")
@settings_options
@one_line_errors
def results_cmd(sweep: str, as_csv: bool, limit: int | None, settings: Callable[..., "Settings"]) -> None:
    """The runs of SWEEP (an id or a name) with their grid values and results, in grid order."""
    from scheduler.query import result_rows

    store = _store(settings(), create=False)
    snap = store.find_sweep(sweep)
    page = store.runs_page(sweep_id=snap.id, limit=limit or (None if as_csv else TABLE_ROWS), newest_first=False)
    rows = result_rows(snap.spec, page.runs)
    if not as_csv:
        click.echo(_table(rows))
        more = "; more with --limit N or --csv" if len(rows) < page.total else ""
        click.echo(f"\n{len(rows)} of {page.total} runs of sweep {snap.name}{_by_state(store.status_counts(snap.id))}{more}")
        return
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["run"], lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    click.echo(buf.getvalue(), nl=False)


COMMANDS = (submit_cmd, worker_cmd, status_cmd, cancel_cmd, resume_cmd, sweep_cmd, results_cmd)
