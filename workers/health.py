"""Runs that cannot make progress: waiting on a queue no live worker consumes, or failing.

Every run's work goes to one of the farm's two queues (:mod:`workers.queues`):
a queued run waits for its start on ``undream.control``; a running or
evaluating run waits on ``undream.frames`` while its current iteration has
jobs queued, started or retried, else on ``undream.control`` for the phase's
callback. Which queues have a live consumer the workers say themselves, in
Redis (:mod:`workers.presence`; :func:`probe` reads it in milliseconds, where
Celery's remote control waits out its whole timeout on every call). A farm run whose queue nobody
consumes is *waiting*; a run whose current iteration has jobs whose last
attempt failed is *failing*, with that job's error (redacted, one line).
A run driven by its own process (``undream run``) uses no queue and is never
waiting.

:func:`probe` never hangs: Redis is reached within the settings'
``connect_timeout``; when it cannot be reached the live queues are *unknown*
(None, with the reason), and no run is called waiting. The store is read in a fixed
number of queries (:meth:`undream.store.Store.stalled_runs`, read only when
a queue has no live worker, and :meth:`~undream.store.Store.failing_runs`), and each list
shows at most ``limit`` runs, those stalled longest first, with the total.
"""
from __future__ import annotations

import datetime as dt
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping

from scheduler.heal import BLIND, FarmView, StallRule, stalled
from scheduler.options import FarmOptions
from undream.redact import redact_text
from undream.store import mask_url
from workers.presence import live_queues, presence, queued_runs, ttl_of
from workers.queues import CONTROL_QUEUE, FRAMES_QUEUE

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.store import Store
    from undream.store.activity import JobError, RunHealth

LIMIT = 20  # runs listed per kind (waiting, failing); the totals are given apart
# queue → what a run waits for there (Store.stalled_runs' kinds): its start or a phase's callback, or its jobs
WAITS_ON = {CONTROL_QUEUE: ("queued", "callback"), FRAMES_QUEUE: ("jobs",)}
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


def _ask(settings: "Settings") -> Consumers:
    try:
        return Consumers(live_queues(settings))
    except Exception as exc:  # redis-py's ConnectionError, TimeoutError, AuthenticationError, a bad URL
        return Consumers(None, f"cannot read the workers' announcements at {mask_url(settings.backend_url)!r}: "
                               f"{one_line(str(exc) or type(exc).__name__)}")


def probe(settings: "Settings") -> Consumers:
    """Which queues have a live worker, from the workers' announcements in Redis
    (:mod:`workers.presence`): milliseconds when Redis answers; ``connect_timeout`` at most to
    reach it, and never longer than twice that plus a second (the reading thread is left behind,
    as a daemon, if Redis stalls)."""
    box: list[Consumers] = []
    reader = threading.Thread(target=lambda: box.append(_ask(settings)), name="undream-probe", daemon=True)
    reader.start()
    limit = 2 * settings.connect_timeout + 1.0
    reader.join(limit)
    if box:
        return box[0]
    return Consumers(None, f"Redis at {mask_url(settings.backend_url)!r} did not answer within {limit:g} s")


def farm_view(settings: "Settings") -> FarmView:
    """What the broker says of the farm's runs (:class:`scheduler.heal.FarmView`): the runs live
    workers hold, from their announcements (unknown until they are complete: see
    :func:`workers.presence.presence`), and the runs with a message waiting in a queue (a queue
    too long to read, or a broker out of reach, leaves its kinds :data:`WAITS_ON` unread).
    Never raises: what cannot be read is unknown, and nothing is called stalled that could be
    held or waiting."""
    try:
        seen = presence(settings)
        held = seen.runs if seen.complete else None
        why = "" if seen.complete else f"not every worker has announced itself yet (Redis started < {ttl_of(settings):g} s ago)"
    except Exception as exc:  # redis-py's ConnectionError, TimeoutError, a URL that is not Redis
        held, why = None, f"cannot read the workers' announcements: {one_line(str(exc) or type(exc).__name__)}"
    try:
        waiting, unread = queued_runs(settings, list(WAITS_ON))
    except Exception as exc:
        return FarmView(held, frozenset(), frozenset(k for kinds in WAITS_ON.values() for k in kinds),
                        f"cannot read the queues: {one_line(str(exc) or type(exc).__name__)}")
    return FarmView(held, waiting, frozenset(k for q in unread for k in WAITS_ON[q]), why)


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


def _stalled_first(row: dict[str, Any]) -> tuple[float, str]:
    return -row["stalled_s"], row["run_id"]


def _stalled(store: "Store", rule: "StallRule | None", view: Callable[[], FarmView], now: dt.datetime,
             shown: set[str], limit: int) -> list[dict[str, Any]]:
    """The farm's stalled runs (:mod:`scheduler.heal`'s rule) not already shown as waiting or failing."""
    if rule is None:
        return []
    found = stalled(store, rule, now, limit + len(shown), view())
    return [{**_base(run, now), "state": "stalled", "reason": why} for run, why in found if run.id not in shown][:limit]


def stuck_runs(store: "Store", consumers: Callable[[], Consumers], now: dt.datetime | None = None,
               limit: int = LIMIT, rule: "StallRule | None" = None,
               view: Callable[[], FarmView] = lambda: BLIND) -> dict[str, Any]:
    """The runs that cannot make progress, as plain data: ``waiting`` and ``failing`` (at most
    ``limit`` each, stalled longest first), their totals ``n_waiting`` (None while the live queues
    are unknown) and ``n_failing``, ``active`` (farm runs queued, running or evaluating), ``queues``
    (queue → live workers; None: unknown, or not asked) and ``broker_error``. ``consumers`` is
    called (the broker asked: ``asked``) only when a farm run is active; the runs waiting are read
    only when a queue has no live worker. ``rule`` given: also ``stalled``, the runs that rule calls
    stalled (:func:`scheduler.heal.stall_reason`: live workers, yet no progress; ``view``: what
    the broker says of the runs, :func:`farm_view`) that are neither waiting nor failing,
    quiet longest first, at most ``limit``. A fixed number of queries,
    whatever the number of runs."""
    now = now or dt.datetime.now(dt.timezone.utc)
    active = store.active_farm_runs()
    live = consumers() if active else Consumers(None)
    dead = [q for q in WAITS_ON if live.queues is not None and not live.queues.get(q)]
    kinds = [kind for q in dead for kind in WAITS_ON[q]]
    counts, stalled = store.stalled_runs(kinds, limit) if kinds else ({}, [])
    waiting = [{**_base(run, now), "state": "waiting", "queue": queue_of(run),
                "reason": f"no live worker on queue {queue_of(run)}"} for run in stalled]
    failing = sorted((_failing(run, err, now) for run, err in store.failing_runs()), key=_stalled_first)
    queues = None if live.queues is None else {q: list(w) for q, w in live.queues.items()}
    shown = {row["run_id"] for row in waiting + failing}
    idle = _stalled(store, rule, view, now, shown, limit) if active else []
    return {"active": active, "asked": bool(active), "queues": queues, "broker_error": live.reason,
            "n_waiting": sum(counts.get(kind, 0) for kind in kinds) if live.known or not active else None,
            "n_failing": len(failing), "waiting": waiting, "failing": failing[:limit], "stalled": idle,
            "now": now.isoformat()}