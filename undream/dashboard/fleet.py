"""The farm's workers as the store sees them: who recorded jobs, what each is doing, jobs per minute.

A worker (``host:pid`` of a worker process) is known by the frame jobs it
started. Only runs that are active or changed within the window are read,
so a long-finished farm costs nothing here. A worker is *busy* while it
holds a started job of an active run, *idle* when it recorded a job start
or finish within ``alive_s`` seconds, else *silent* (stopped, or lost: its
jobs are redelivered by the broker). The store cannot see a worker that
has never taken a job; Celery's own events (Flower) can. :func:`farm_overview`
adds the runs that cannot make progress (:mod:`workers.health`): waiting on a
queue no live worker consumes, or failing.
"""
from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Any

from undream.dashboard.query import iso
from scheduler.heal import StallRule
from workers.health import farm_view, probe, stuck_runs

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.store import Store

WINDOW_S = 600.0  # jobs per minute are counted over this many seconds
ALIVE_S = 120.0  # a worker that recorded nothing for this long and holds no job is silent


def _worker(workers: dict[str, dict[str, Any]], name: str, seen: dt.datetime | None) -> dict[str, Any]:
    w = workers.setdefault(name, {"worker": name, "current": [], "finished": 0, "failed": 0, "last_seen": seen})
    if seen is not None and (w["last_seen"] is None or seen > w["last_seen"]):
        w["last_seen"] = seen
    return w


def workers_overview(store: "Store", now: dt.datetime | None = None, window_s: float = WINDOW_S,
                     alive_s: float = ALIVE_S) -> dict[str, Any]:
    """Each worker seen in the window: state, current jobs, jobs finished and per minute, last seen.

    Two queries whatever the number of runs and jobs (:meth:`undream.store.Store.worker_activity`).
    """
    now = now or dt.datetime.now(dt.timezone.utc)
    since = now - dt.timedelta(seconds=window_s)
    tallies, held = store.worker_activity(since)
    workers: dict[str, dict[str, Any]] = {}
    for t in tallies:
        seen = max((s for s in (t.last_started, t.last_finished) if s is not None), default=None)
        w = _worker(workers, t.worker, seen)
        if t.status != "started":
            w["finished" if t.status == "succeeded" else "failed"] += t.finished
    for job in held:
        w = _worker(workers, job.worker, job.started)
        w["current"].append({"run_id": job.run_id, "run": job.run, "phase": job.phase, "k": job.k,
                             "frame": job.frame, "started": iso(job.started),
                             "running_s": (now - job.started).total_seconds() if job.started else None})
    rows = []
    for w in sorted(workers.values(), key=lambda w: w["worker"]):
        idle_s = (now - w["last_seen"]).total_seconds() if w["last_seen"] else None
        state = "busy" if w["current"] else ("idle" if idle_s is not None and idle_s <= alive_s else "silent")
        rows.append({**w, "state": state, "alive": state != "silent",
                     "jobs_per_minute": w["finished"] / (window_s / 60.0), "last_seen": iso(w["last_seen"]),
                     "idle_s": idle_s})
    return {"window_s": window_s, "alive_s": alive_s, "workers": rows,
            "alive": sum(r["alive"] for r in rows), "now": iso(now)}


def farm_overview(store: "Store", settings: "Settings", now: dt.datetime | None = None) -> dict[str, Any]:
    """:func:`workers_overview` and, under ``stuck``, the runs that cannot make progress
    (:func:`workers.health.stuck_runs`: the broker asked which queues have a live worker, within
    the settings' ``connect_timeout``, only while a farm run is active; and the runs stalled by the
    healer's rule, :mod:`scheduler.heal`). A fixed number of queries, whatever the number of runs."""
    now = now or dt.datetime.now(dt.timezone.utc)
    stuck = stuck_runs(store, lambda: probe(settings), now, rule=StallRule.of(settings),
                       view=lambda: farm_view(settings))
    return {**workers_overview(store, now), "stuck": stuck}
