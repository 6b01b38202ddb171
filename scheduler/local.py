"""The whole run in one process: the farm's stages, drained from a queue.

:func:`run_local` records the run, then runs what the stages dispatch in
order: the start, each phase's per-frame jobs, its callback (which
dispatches the next phase). It is the farm without Celery: the same
functions (:mod:`scheduler.stages`), the same store, the same outputs.
"""
from __future__ import annotations

import logging
import shutil
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scheduler import stages
from scheduler.options import attacked_positions
from scheduler.preflight import (check_output_folder, claim_output, is_run_output, is_scene, preflight, scene_source,
                                 scene_sources)
from undream import interrupts
from undream.scenedir.conditions import conditions_sequence
from undream.scenedir.init import InitOptions, init_scene
from undream.settings import LocalSettings
from undream.errors import SpecError, UndreamError
from undream.progress import progress as progress_bar
from undream.spec.io import join_against
from undream.spec.run import RunConfig

if TYPE_CHECKING:  # torch loads once the checks have passed: a refusal is quick
    from undream.engine.context import RunContext

log = logging.getLogger(__name__)

__all__ = ["LocalDispatch", "RunFailed", "check_run", "drain", "resolve_scene", "resume_local", "run_local"]

# In one process a failure is rarely transient: one retry, then the run fails with the error.
LOCAL_OPTIONS = {"max_attempts": 2, "failure_budget": 0}


class RunFailed(UndreamError):
    """A run ended failed (the message is the run's error)."""


def resolve_scene(config: RunConfig, out: Path, base_dir: Path, reuse: bool = False,
                  local: LocalSettings = LocalSettings()) -> Path:
    """The run's scene directory: given, or initialised from a spec file (or a multi-condition run's
    scenes, :mod:`undream.scenedir.conditions`) into ``out/scene`` (``reuse``: the one an earlier start of the run already initialised there, if any;
    ``local``: this process's settings, read at the edge: the memory limit)."""
    src = join_against(config.scene, base_dir)
    if is_scene(src) and config.conditions is None:
        return src
    if not src.exists():
        raise SpecError(f"scene: {src} is neither a scene directory nor a spec file")
    if reuse and is_scene(out / "scene"):
        return out / "scene"
    if config.conditions is not None:  # every condition's frames in one scene directory
        src = conditions_sequence(config, base_dir, local.undream_cache)
    return init_scene(src, out / "scene", InitOptions(force=True, memory_limit=local.memory_limit, frozen=local.frozen,
                                                      cache_dir=local.undream_cache))


class LocalDispatch:
    """A :class:`scheduler.stages.Dispatch` that queues the work for :func:`drain`."""

    def __init__(self) -> None:
        self.queue: deque[tuple[Any, ...]] = deque()

    def start(self, run_id: str) -> None:
        self.queue.append(("start", run_id))

    def frames(self, run_id: str, phase: str, k: int, batches: list[list[int]]) -> None:
        self.queue.append(("frames", run_id, phase, k, batches))


def drain(store: Any, contexts: stages.Contexts, dispatch: LocalDispatch,
          on_collect: Any = None, benign: Any = None) -> None:
    """Run everything queued, and what it queues, until nothing is left.

    A batch whose jobs failed with attempts left runs again at once; each
    phase's callback follows its jobs. ``on_collect(run_id, phase, k, outcome)``
    is called after each callback. ``benign``: the blob store that keeps benign
    evaluations (:func:`benign_blobs`; None: the run store's).
    """
    while dispatch.queue:
        interrupts.check()  # a stop whose exception was dropped (raised in a __del__) ends the run here
        item = dispatch.queue.popleft()
        if item[0] == "start":
            stages.start(store, contexts, item[1], dispatch)
            continue
        _, run_id, phase, k, batches = item
        for batch in batches:
            interrupts.check()
            while stages.run_batch(store, contexts, run_id, phase, k, batch, benign=benign)["retry"]:
                pass
        outcome = stages.collect(store, contexts, run_id, phase, k, dispatch)
        if on_collect is not None:
            on_collect(run_id, phase, k, outcome)


def run_local(config: RunConfig, out: str | Path, base_dir: Path | None = None, progress: bool = True,
              force: bool = False, resume: bool = False, source: Path | None = None,
              local: LocalSettings = LocalSettings()) -> dict[str, Any]:
    """Run an attack end to end in this process and write its outputs to ``out``; returns results.

    Everything is validated before ``out`` is created or replaced
    (:mod:`scheduler.preflight`): ``force`` only replaces a folder an earlier
    run wrote, never one holding the run's scene or spec. ``resume``
    continues the run recorded in ``out`` instead (see :func:`resume_local`).
    ``source``: the run config's file, named in validation errors. ``local``:
    this process's settings, read at the edge (:func:`undream.settings.load_local`).

    The process holds the run's lease while it runs (:class:`scheduler.lease.Lease`),
    so a run whose process is killed is found stale, marked failed and can be resumed.
    A run that fails (every frame non-finite, a frame job failing twice) is
    marked failed in the store with the error, which is raised
    (:class:`scheduler.iteration.AllFramesFailed`, :class:`RunFailed`).
    """
    from undream.store import open_store

    out, base_dir = Path(out).resolve(), base_dir or Path.cwd()
    if resume:
        if force:
            raise SpecError("--resume continues the run in --out and --force replaces it: give one of them")
        return resume_local(config, out, base_dir, progress, source, local)
    check_output_folder(out, scene_source(config, base_dir), force, inputs=(source, *scene_sources(config, base_dir)[1:]))  # cheap refusals first
    replace = out.exists() and any(out.iterdir())  # as checked: --force and a folder `undream run` wrote
    victim = preflight(config, base_dir, source, local).victim  # nothing written or deleted before this passes
    from undream.engine.context import build_context  # torch: after the checks, so a refusal is quick

    if replace:
        shutil.rmtree(out)
    claim_output(out, config)  # atomic: a run that claimed a new --out since the check keeps it whole
    try:  # until the run is recorded, a failure (a scene whose init fails, a signal) removes what it wrote
        scene_dir = resolve_scene(config, out, base_dir, local=local)
        ctx: RunContext = build_context(config, scene_dir, victim=victim, local=local)
        store = open_store(config.store, out / "store")
        n = len(ctx.sequence.frames)
        options = stages.FarmOptions(frames_per_task=n, **LOCAL_OPTIONS,
                                     attacked=attacked_positions(config, ctx.sequence),
                                     benign_cache=local.benign_cache)
        run_id = stages.create(store, config, n, options, out_dir=str(out))
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return _drive(store, ctx, run_id, progress, lambda dispatch: dispatch.start(run_id),
                  benign=benign_blobs(local))


def benign_blobs(local: LocalSettings) -> Any:
    """Where ``undream run`` keeps benign evaluations for later runs (:mod:`scheduler.benign`): the
    folder ``<cache_home>/undream`` (keys ``benign/<key>/...``), shared by every run of this user."""
    from undream.store import BlobStore

    return BlobStore(Path(local.cache_home) / "undream")


def check_run(config: RunConfig, out: str | Path, base_dir: Path | None = None,
              force: bool = False, source: Path | None = None, local: LocalSettings = LocalSettings()) -> Any:
    """``undream run --check``: every check :func:`run_local` makes before it writes, nothing
    written; the run's estimate (:class:`undream.render.budget.Estimate`)."""
    out, base_dir = Path(out).resolve(), base_dir or Path.cwd()
    check_output_folder(out, scene_source(config, base_dir), force, inputs=(source, *scene_sources(config, base_dir)[1:]))
    return preflight(config, base_dir, source, local).estimate


def resume_local(config: RunConfig, out: Path, base_dir: Path, progress: bool = True,
                 source: Path | None = None, local: LocalSettings = LocalSettings()) -> dict[str, Any]:
    """Continue the run that ``undream run`` recorded in ``out`` (after a crash, a kill or Ctrl-C).

    The run config must be the one the run was started with. A run whose
    process is gone is marked failed first (:func:`scheduler.lease.expire_stale`);
    one still driven by a live process is refused. The run goes on from its
    last completed iteration with the same seeds, so it ends where an
    uninterrupted run would. A run already done returns its results.
    """
    from scheduler.lease import expire_stale
    from undream.store import open_store

    if not is_run_output(out):
        raise SpecError(f"--out {out}: --resume continues a run that `undream run` started there, "
                        "and this folder has none (no metadata.json of a run)")
    victim = preflight(config, base_dir, source, local).victim
    from undream.engine.context import build_context  # torch: after the checks

    store = open_store(config.store, out / "store")
    run = _recorded_run(store, config, out)
    expire_stale(store, [run])
    run = store.get_run(run.id)
    if run.status == "done":
        return run.results or {}
    ctx = build_context(config, resolve_scene(config, out, base_dir, reuse=True, local=local), victim=victim,
                        local=local)
    return _drive(store, ctx, run.id, progress, lambda dispatch: stages.resume(store, run.id, dispatch),
                  done=run.iteration, benign=benign_blobs(local))


def _recorded_run(store: Any, config: RunConfig, out: Path) -> Any:
    """The run of ``config`` that ``undream run`` recorded for ``out``; SpecError naming what differs."""
    runs = [r for r in store.runs() if r.out_dir and Path(r.out_dir).resolve() == out]
    if not runs:
        raise SpecError(f"--out {out}: no run is recorded for this folder in its store; nothing to resume")
    run = runs[-1]
    stored, wanted = run.run_config.to_json(), config.to_json()  # both complete: defaults filled in
    changed = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
    if changed:
        raise SpecError(f"--out {out}: run {run.id} was started with another config "
                        f"({', '.join(changed)} differ); resume it with the config it started with")
    return run


def _drive(store: Any, ctx: RunContext, run_id: str, progress: bool,
           first: Any, done: int = 0, benign: Any = None) -> dict[str, Any]:
    """Hold the run's lease and drain its stages from ``first(dispatch)``; the run's results.

    A failure while the lease is held marks the run failed with the error; a
    lease refused (a live process drives the run) touches nothing.
    """
    from scheduler.lease import Lease

    dispatch = LocalDispatch()
    with Lease(store, run_id):
        bar = progress_bar(ctx.attack.config.steps, "attack", "it", progress)
        bar.update(done)

        def on_collect(run_id: str, phase: str, k: int, outcome: str) -> None:
            if phase == "attack" and outcome == "stepped":
                rec = store.iterations(run_id)[-1]
                bar.update(1)
                bar.set_postfix(loss="n/a" if rec.loss_mean is None else f"{rec.loss_mean:.4f}",
                                bad=rec.n_bad)

        try:
            first(dispatch)
            drain(store, lambda _: ctx, dispatch, on_collect, benign)
        except BaseException as exc:
            error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
            store.transition(run_id, ("queued", "running", "evaluating"), "failed", error=error)
            raise
        finally:
            bar.close()
    run = store.get_run(run_id)
    if run.status != "done":
        raise RunFailed(f"run {run_id}: {run.status}: {run.error}")
    return run.results or {}
