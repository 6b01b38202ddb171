"""The farm's tasks: ids and JSON in → one scheduler stage → small JSON out.

``undream.start`` (run_id), ``undream.frames`` (run_id, phase, k, frames: a
batch of frame positions) and ``undream.collect`` (run_id, phase, k: the
chord's callback). Arrays never travel: jobs read and write the blob store.
A batch whose jobs failed with attempts left is retried by Celery (the
attempts are counted in the store, which caps them); a store that cannot be
reached is retried with back-off; any other error of a stage fails the run
with that error, so a run never stays running for ever (``undream resume``
starts it again).
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Callable

from undream.errors import StoreError

if TYPE_CHECKING:
    from celery import Celery, Task

log = logging.getLogger(__name__)

TASK_NAMES = ("undream.start", "undream.frames", "undream.collect")
RETRY_DELAY_S = 0.5


def _guard(app: "Celery", run_id: str, fn: Callable[[], Any]) -> Any:
    """Run a stage; any error but the store's fails the run with its message (`undream resume` restarts it)."""
    from workers.runtime import runtime

    try:
        return fn()
    except StoreError:
        raise  # the database or blob store is away: Celery retries with back-off
    except Exception as err:  # an output folder not writable, the broker gone mid-dispatch, a bug
        error = f"{type(err).__name__}: {' '.join(str(err).split())}"
        log.error("run %s failed: %s", run_id, error)
        runtime(app).store.transition(run_id, ("queued", "running", "evaluating"), "failed", error=error)
        return "failed"


def register_tasks(app: "Celery") -> None:
    """Declare the tasks on ``app`` (called by :func:`workers.app.create_celery_app`)."""
    from scheduler import stages
    from workers.runtime import runtime

    common: dict[str, Any] = {"bind": True, "shared": False, "acks_late": True, "reject_on_worker_lost": True,
                              "autoretry_for": (StoreError,), "retry_backoff": 1,
                              "retry_backoff_max": 30, "max_retries": 10}

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

    @app.task(name="undream.collect", **common)
    def collect(self: "Task", run_id: str, phase: str, k: int) -> dict[str, Any]:
        rt = runtime(app)
        outcome = _guard(app, run_id, lambda: stages.collect(rt.store, rt.contexts, run_id, phase, k,
                                                             rt.dispatch))
        return {"run_id": run_id, "phase": phase, "k": k, "outcome": outcome}
