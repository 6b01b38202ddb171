"""The farm's tasks: ids and JSON in → one scheduler stage → small JSON out.

``undream.start`` (run_id), ``undream.frames`` (run_id, phase, k, frames: a
batch of frame positions) and ``undream.collect`` (run_id, phase, k: the
chord's callback); and ``undream.heal`` (the sending worker's name: one heal
pass over the farm's stalled runs, :mod:`workers.healer`). Arrays never travel: jobs read and write the blob store.
A batch whose jobs failed with attempts left is retried by Celery (the
attempts are counted in the store, which caps them); a store that cannot be
reached is retried with back-off (``store_retries`` times); any other error
of a stage fails the run with that error, and so does a task that gives up
(its retries used up, or an error outside a stage), so a run never stays
queued or running for ever (``undream resume`` starts it again).
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Callable

from scheduler.heal import StallRule
from scheduler.heal import heal as heal_pass
from undream.errors import StoreError
from workers.healer import HEAL_TASK
from workers.health import farm_view
from workers.runtime import runtime

if TYPE_CHECKING:
    from celery import Celery, Task

log = logging.getLogger(__name__)

TASK_NAMES = ("undream.start", "undream.frames", "undream.collect")
RETRY_DELAY_S = 0.5


def _guard(app: "Celery", run_id: str, fn: Callable[[], Any]) -> Any:
    """Run a stage; any error but the store's fails the run with its message (`undream resume` restarts it)."""
    try:
        return fn()
    except StoreError:
        raise  # the database or blob store is away: Celery retries with back-off
    except Exception as err:  # an output folder not writable, the broker gone mid-dispatch, a bug
        error = f"{type(err).__name__}: {' '.join(str(err).split())}"
        log.error("run %s failed: %s", run_id, error)
        runtime(app).store.transition(run_id, ("queued", "running", "evaluating"), "failed", error=error)
        return "failed"


def _what(task_name: str, args: tuple, kwargs: dict) -> str:
    """The stage a task ran, in words (``start``, ``attack k=3 frames 0, 1``, ``pre k=5 callback``)."""
    names = {"undream.start": ("run_id",), "undream.frames": ("run_id", "phase", "k", "frames"),
             "undream.collect": ("run_id", "phase", "k")}.get(task_name, ("run_id",))
    call = {**dict(zip(names, args)), **kwargs}
    if task_name == "undream.frames":
        return f"{call.get('phase')} k={call.get('k')} frames {', '.join(map(str, call.get('frames') or []))}"
    if task_name == "undream.collect":
        return f"{call.get('phase')} k={call.get('k')} callback"
    return "start"


def give_up(app: "Celery", task: "Task", exc: BaseException, args: tuple, kwargs: dict) -> None:
    """A task failed for good (its store retries used up, or an error no stage caught): its run
    fails with why, in one line, so it never stays queued or running for ever."""
    run_id = args[0] if args else kwargs.get("run_id")
    retries = task.request.retries
    how = f"gave up after {retries} {'retry' if retries == 1 else 'retries'}" if retries else "failed"
    error = f"{_what(task.name, args, kwargs)} {how}: {type(exc).__name__}: {' '.join(str(exc).split())}"
    log.error("run %s failed: %s", run_id, error)
    try:
        runtime(app).store.transition(run_id, ("queued", "running", "evaluating"), "failed", error=error)
    except Exception as err:  # the database itself is away: the log line is all there can be
        log.error("run %s: cannot record its failure: %s", run_id, " ".join(str(err).split()))


def register_tasks(app: "Celery") -> None:
    """Declare the tasks on ``app`` (called by :func:`workers.app.create_celery_app`)."""
    from celery import Task

    from scheduler import stages

    class RunTask(Task):
        """A task of one run (its first argument): when it fails for good, so does the run."""

        def on_failure(self, exc: BaseException, task_id: str, args: tuple, kwargs: dict,
                       einfo: Any) -> None:
            give_up(app, self, exc, tuple(args), dict(kwargs))

    retries = app.undream_settings.store_retries  # type: ignore[attr-defined]
    common: dict[str, Any] = {"base": RunTask, "bind": True, "shared": False, "acks_late": True,
                              "reject_on_worker_lost": True, "autoretry_for": (StoreError,),
                              "retry_backoff": 1, "retry_backoff_max": 30, "max_retries": retries}

    @app.task(name="undream.start", **common)
    def start(self: "Task", run_id: str) -> dict[str, Any]:
        rt = runtime(app)
        outcome = _guard(app, run_id, lambda: stages.start(rt.store, rt.contexts, run_id, rt.dispatch))
        return {"run_id": run_id, "outcome": outcome}

    @app.task(name="undream.frames", **common)
    def frames(self: "Task", run_id: str, phase: str, k: int, frames: list[int]) -> dict[str, Any]:
        rt = runtime(app)
        summary = stages.run_batch(rt.store, rt.contexts, run_id, phase, k, frames, rt.textures)
        if summary["retry"]:
            raise self.retry(countdown=RETRY_DELAY_S, max_retries=None)
        return summary

    @app.task(name=HEAL_TASK, bind=True, shared=False, acks_late=True, ignore_result=True)
    def heal(self: "Task", by: str) -> dict[str, Any]:
        """One heal pass (:mod:`workers.healer`): the farm's stalled runs' current work sent again."""
        rt, settings = runtime(app), app.undream_settings  # type: ignore[attr-defined]
        healed = heal_pass(rt.store, rt.dispatch, StallRule.of(settings), by=f"undream worker {by}",
                           view=lambda: farm_view(settings))
        return {"healed": healed}

    @app.task(name="undream.collect", **common)
    def collect(self: "Task", run_id: str, phase: str, k: int) -> dict[str, Any]:
        rt = runtime(app)
        outcome = _guard(app, run_id, lambda: stages.collect(rt.store, rt.contexts, run_id, phase, k,
                                                             rt.dispatch))
        return {"run_id": run_id, "phase": phase, "k": k, "outcome": outcome}
