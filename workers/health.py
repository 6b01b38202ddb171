"""Runs that cannot make progress: waiting on a queue no live worker consumes, or failing.

Every run's work goes to one of the farm's two queues (:mod:`workers.queues`):
a queued run waits for its start on ``undream.control``; a running or
evaluating run waits on ``undream.frames`` while its current iteration has
jobs queued, started or retried, else on ``undream.control`` for the phase's
callback. Which queues have a live consumer is asked of the workers
themselves through Celery's remote control (:func:`probe`: every worker
answers ``active_queues`` within a second). A farm run whose queue nobody
consumes is *waiting*; a run whose current iteration has jobs whose last
attempt failed is *failing*, with that job's error (redacted, one line).
A run driven by its own process (``undream run``) uses no queue and is never
waiting.

:func:`probe` never hangs: the broker is reached within the settings'
``connect_timeout`` and the replies are awaited :data:`REPLY_S` at most;
when the broker cannot be reached the live queues are *unknown* (None, with
the reason), and no run is called waiting. The store is read in a fixed
number of queries (:meth:`undream.store.Store.run_health`), and each list
shows at most ``limit`` runs, those stalled longest first, with the total.
"""
from __future__ import annotations

import datetime as dt
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping

from scheduler.stages import FarmOptions
from undream.redact import redact_text
from undream.store import mask_url
from workers.app import BrokerError, check_reachable, create_celery_app
from workers.queues import CONTROL_QUEUE, FRAMES_QUEUE

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.store import Store
    from undream.store.activity import JobError, RunHealth

REPLY_S = 1.0  # s to wait for the workers' answers (at most the settings' connect_timeout)
LIMIT = 20  # runs listed per kind (waiting, failing); the totals are given apart
ERROR_WIDTH = 160  # characters of a job's error shown


@dataclass(frozen=True)
class Consumers:
    """The farm's live queues as the workers answered: queue name → the workers (Celery node
    names) consuming it; ``queues`` None when unknown, with ``reason`` (the broker cannot be
    reached, or did not answer)."""

    queues: Mapping[str, tuple[str, ...]] | None
    reason: str | None = None

    @property
    def known(self) -> bool:
        return self.queues is not None


def _ask(settings: "Settings", reply_s: float) -> Consumers:
    try:
        app = create_celery_app(settings)
    except Exception as exc:  # bad local settings in the environment: say so, never raise here
        return Consumers(None, f"cannot build the Celery app: {one_line(str(exc) or type(exc).__name__)}")
    try:
        check_reachable(app, settings)
        replies = app.control.inspect(timeout=reply_s).active_queues() or {}
    except BrokerError as err:
        return Consumers(None, one_line(str(err)))
    except Exception as exc:  # kombu's OperationalError and the transport's own errors
        return Consumers(None, f"cannot ask the workers through {mask_url(settings.broker_url)!r}: "
                               f"{one_line(str(exc) or type(exc).__name__)}")
    finally:
        app.close()
    queues: dict[str, list[str]] = {}
    for worker, consumed in replies.items():
        for queue in consumed or ():
            queues.setdefault(queue.get("name", "?"), []).append(worker)
    return Consumers({q: tuple(sorted(ws)) for q, ws in sorted(queues.items())})


def probe(settings: "Settings", reply_s: float = REPLY_S) -> Consumers:
    """Which queues have a live worker, asked through the broker: at most ``connect_timeout`` to
    reach it, ``min(reply_s, connect_timeout)`` for the answers, and never longer than their sum
    plus a second (the asking thread is left behind, as a daemon, if the broker stalls)."""
    wait = min(reply_s, settings.connect_timeout)
    box: list[Consumers] = []
    asker = threading.Thread(target=lambda: box.append(_ask(settings, wait)), name="undream-probe", daemon=True)
    asker.start()
    asker.join(settings.connect_timeout + wait + 1.0)
    if box:
        return box[0]
    return Consumers(None, f"the broker at {mask_url(settings.broker_url)!r} did not answer within "
                           f"{settings.connect_timeout + wait + 1.0:g} s")


def one_line(text: str, width: int = ERROR_WIDTH) -> str:
    """``text`` redacted (:func:`undream.redact.redact_text`), on one line, cut to ``width`` characters."""
    text = " ".join(redact_text(text).split())
    return text if len(text) <= width else text[: width - 1] + "…"


def queue_of(run: "RunHealth") -> str:
    """The queue the run's next work waits on (see the module's docstring)."""
    if run.status == "queued":
        return CONTROL_QUEUE
    return FRAMES_QUEUE if run.unfinished else CONTROL_QUEUE


def _since(run: "RunHealth") -> dt.datetime:
    """When the run last progressed: its row's last change or its current jobs' latest start or finish."""
    return max(run.updated, run.last_job) if run.last_job else run.updated


def _base(run: "RunHealth", now: dt.datetime) -> dict[str, Any]:
    since = _since(run)
    return {"run_id": run.id, "run": run.name, "status": run.status, "iteration": run.iteration,
            "since": since.isoformat(), "stalled_s": max(0.0, (now - since).total_seconds())}


def _failing(run: "RunHealth", err: "JobError", now: dt.datetime) -> dict[str, Any]:
    reason = one_line(err.error) or "(no message)"
    options = FarmOptions.of(run)  # type: ignore[arg-type]  # reads the run's ``farm`` only
    return {**_base(run, now), "state": "failing", "reason": reason,
            "job": f"{err.phase} k={err.k} frame {err.frame}", "job_status": err.status,
            "attempts": err.attempts, "max_attempts": options.max_attempts,
            "failed_jobs": run.errored, "failures": run.failures,
            "failure_budget": options.failure_budget}


def diagnose(runs: list["RunHealth"], errors: Mapping[str, "JobError"], consumers: Consumers,
             now: dt.datetime) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(waiting, failing): the farm runs whose queue has no live worker (none while the live queues
    are unknown), and the runs with an error at their current iteration; each list the runs stalled
    longest first. Plain data; no query, no broker."""
    waiting, failing = [], []
    for run in runs:
        if consumers.queues is not None and run.owner is None:
            queue = queue_of(run)
            if not consumers.queues.get(queue):
                waiting.append({**_base(run, now), "state": "waiting", "queue": queue,
                                "reason": f"no live worker on queue {queue}"})
        if run.id in errors:
            failing.append(_failing(run, errors[run.id], now))
    return sorted(waiting, key=_stalled_first), sorted(failing, key=_stalled_first)


def _stalled_first(row: dict[str, Any]) -> tuple[float, str]:
    return -row["stalled_s"], row["run_id"]


def stuck_runs(store: "Store", consumers: Callable[[], Consumers], now: dt.datetime | None = None,
               limit: int = LIMIT) -> dict[str, Any]:
    """The runs that cannot make progress, as plain data: ``waiting`` and ``failing`` (at most
    ``limit`` each, stalled longest first), their totals ``n_waiting`` (None while the live queues
    are unknown) and ``n_failing``, ``queues`` (queue → live workers; None: unknown, or not asked)
    and ``broker_error``. ``consumers`` is called (the broker asked: ``asked``) only when a farm
    run is active. Two queries, whatever the number of runs."""
    now = now or dt.datetime.now(dt.timezone.utc)
    runs, errors = store.run_health()
    asked = any(r.owner is None for r in runs)
    live = consumers() if asked else Consumers(None)
    waiting, failing = diagnose(runs, errors, live, now)
    queues = None if live.queues is None else {q: list(w) for q, w in live.queues.items()}
    return {"active": len(runs), "asked": asked, "queues": queues, "broker_error": live.reason,
            "n_waiting": len(waiting) if live.known or not asked else None, "n_failing": len(failing),
            "waiting": waiting[:limit], "failing": failing[:limit], "now": now.isoformat()}
