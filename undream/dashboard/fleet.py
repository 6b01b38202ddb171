"""The farm's workers as the store sees them: who recorded jobs, what each is doing, jobs per minute.

A worker (``host:pid`` of a worker process) is known by the frame jobs it
started. Only runs that are active or changed within the window are read,
so a long-finished farm costs nothing here. A worker is *busy* while it
holds a started job of an active run, *idle* when it recorded a job start
or finish within ``alive_s`` seconds, else *silent* (stopped, or lost: its
jobs are redelivered by the broker). The store cannot see a worker that
has never taken a job; Celery's own events (Flower) can.
"""
from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Any

from undream.dashboard.query import ACTIVE_STATUSES, iso

if TYPE_CHECKING:
    from undream.store import JobSnapshot, RunSnapshot, Store

WINDOW_S = 600.0  # jobs per minute are counted over this many seconds
ALIVE_S = 120.0  # a worker that recorded nothing for this long and holds no job is silent


def _recent_jobs(store: "Store", runs: list["RunSnapshot"]) -> list[tuple["RunSnapshot", "JobSnapshot"]]:
    out = []
    for run in runs:
        jobs = store.jobs(run.id, None, "attack")
        jobs += [j for phase in ("pre", "adversarial") for j in store.jobs(run.id, run.iteration, phase)]
        out += [(run, j) for j in jobs if j.worker]
    return out


def _last_seen(job: "JobSnapshot") -> dt.datetime | None:
    stamps = [s for s in (job.started, job.finished) if s is not None]
    return max(stamps) if stamps else None


def workers_overview(store: "Store", now: dt.datetime | None = None, window_s: float = WINDOW_S,
                     alive_s: float = ALIVE_S) -> dict[str, Any]:
    """Each worker seen in the window: state, current jobs, jobs finished and per minute, last seen."""
    now = now or dt.datetime.now(dt.timezone.utc)
    since = now - dt.timedelta(seconds=window_s)
    runs = [r for r in store.runs() if r.status in ACTIVE_STATUSES or r.updated >= since]
    workers: dict[str, dict[str, Any]] = {}
    for run, job in _recent_jobs(store, runs):
        seen = _last_seen(job)
        if seen is None or (seen < since and not (job.status == "started" and run.status in ACTIVE_STATUSES)):
            continue
        w = workers.setdefault(job.worker, {"worker": job.worker, "current": [], "finished": 0,
                                            "failed": 0, "last_seen": seen})  # type: ignore[index]
        w["last_seen"] = max(w["last_seen"], seen)
        if job.status == "started" and run.status in ACTIVE_STATUSES:
            w["current"].append({"run_id": run.id, "run": run.name, "phase": job.phase, "k": job.k,
                                 "frame": job.frame, "started": iso(job.started),
                                 "running_s": (now - job.started).total_seconds() if job.started else None})
        elif job.finished is not None and job.finished >= since:
            w["finished" if job.status == "succeeded" else "failed"] += 1
    rows = []
    for w in sorted(workers.values(), key=lambda w: w["worker"]):
        idle_s = (now - w["last_seen"]).total_seconds()
        state = "busy" if w["current"] else ("idle" if idle_s <= alive_s else "silent")
        rows.append({**w, "state": state, "alive": state != "silent",
                     "jobs_per_minute": w["finished"] / (window_s / 60.0), "last_seen": iso(w["last_seen"]),
                     "idle_s": idle_s})
    return {"window_s": window_s, "alive_s": alive_s, "workers": rows,
            "alive": sum(r["alive"] for r in rows), "now": iso(now)}
