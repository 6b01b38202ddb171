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
from typing import Any

from scheduler import stages
from scheduler.texture0 import starting_texture, visibility
from undream.engine.context import RunContext, build_context
from undream.errors import SpecError, UndreamError
from undream.progress import progress as progress_bar
from undream.spec.run import RunConfig

log = logging.getLogger(__name__)

__all__ = ["LocalDispatch", "RunFailed", "drain", "resolve_scene", "run_local", "starting_texture",
           "visibility"]

# In one process a failure is rarely transient: one retry, then the run fails with the error.
LOCAL_OPTIONS = {"max_attempts": 2, "failure_budget": 0}


class RunFailed(UndreamError):
    """A run ended failed (the message is the run's error)."""


def resolve_scene(config: RunConfig, out: Path, base_dir: Path) -> Path:
    """The run's scene directory: given, or initialised from a spec file into ``out/scene``."""
    from undream.scenedir.init import InitOptions, init_scene

    src = Path(config.scene)
    if not src.is_absolute():
        src = base_dir / src
    if (src / "sequence.json").is_file():
        return src
    if not src.exists():
        raise SpecError(f"scene: {src} is neither a scene directory nor a spec file")
    return init_scene(src, out / "scene", InitOptions(force=True))


class LocalDispatch:
    """A :class:`scheduler.stages.Dispatch` that queues the work for :func:`drain`."""

    def __init__(self) -> None:
        self.queue: deque[tuple[Any, ...]] = deque()

    def start(self, run_id: str) -> None:
        self.queue.append(("start", run_id))

    def frames(self, run_id: str, phase: str, k: int, batches: list[list[int]]) -> None:
        self.queue.append(("frames", run_id, phase, k, batches))


def drain(store: Any, contexts: stages.Contexts, dispatch: LocalDispatch,
          on_collect: Any = None) -> None:
    """Run everything queued, and what it queues, until nothing is left.

    A batch whose jobs failed with attempts left runs again at once; each
    phase's callback follows its jobs. ``on_collect(run_id, phase, k, outcome)``
    is called after each callback.
    """
    while dispatch.queue:
        item = dispatch.queue.popleft()
        if item[0] == "start":
            stages.start(store, contexts, item[1], dispatch)
            continue
        _, run_id, phase, k, batches = item
        for batch in batches:
            while stages.run_batch(store, contexts, run_id, phase, k, batch)["retry"]:
                pass
        outcome = stages.collect(store, contexts, run_id, phase, k, dispatch)
        if on_collect is not None:
            on_collect(run_id, phase, k, outcome)


def run_local(config: RunConfig, out: str | Path, base_dir: Path | None = None, progress: bool = True,
              force: bool = False) -> dict[str, Any]:
    """Run an attack end to end in this process and write its outputs to ``out``; returns results.

    Everything is validated before ``out`` is created or replaced
    (:mod:`scheduler.preflight`): ``force`` only replaces a folder an earlier
    run wrote, never one holding the run's scene or spec.

    A run that fails (every frame non-finite, a frame job failing twice) is
    marked failed in the store with the error, which is raised
    (:class:`scheduler.iteration.AllFramesFailed`, :class:`RunFailed`).
    """
    from scheduler.preflight import check_output_folder, mark_output, preflight, scene_source
    from undream.store import open_store

    out, base_dir = Path(out), base_dir or Path.cwd()
    check_output_folder(out, scene_source(config, base_dir), force)  # cheap refusals first
    victim = preflight(config, base_dir)  # nothing written or deleted before this passes
    if out.exists() and any(out.iterdir()):
        shutil.rmtree(out)  # check_output_folder: --force and a folder `undream run` wrote
    out.mkdir(parents=True, exist_ok=True)
    mark_output(out, config)
    scene_dir = resolve_scene(config, out, base_dir)
    ctx: RunContext = build_context(config, scene_dir, victim=victim)
    store = open_store(config.store, out / "store")
    n = len(ctx.sequence.frames)
    run_id = stages.create(store, config, n, stages.FarmOptions(frames_per_task=n, **LOCAL_OPTIONS),
                           out_dir=str(out))
    bar = progress_bar(ctx.attack.config.steps, "attack", "it", progress)

    def on_collect(run_id: str, phase: str, k: int, outcome: str) -> None:
        if phase == "attack" and outcome == "stepped":
            rec = store.iterations(run_id)[-1]
            bar.update(1)
            bar.set_postfix(loss="n/a" if rec.loss_mean is None else f"{rec.loss_mean:.4f}", bad=rec.n_bad)

    dispatch = LocalDispatch()
    dispatch.start(run_id)
    try:
        drain(store, lambda _: ctx, dispatch, on_collect)
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
