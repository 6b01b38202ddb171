"""Runs heal: a farm run that makes no progress has its current work sent again, by the farm.

The stall rule (:func:`stall_reason`) looks at the farm's active runs in
which nothing happened for ``heal_after`` seconds (the run's row unchanged,
no job of its current iteration started or finished since:
:meth:`undream.store.Store.quiet_runs`), and calls one *stalled* when

- it is ``queued``: its start was never run (lost with the broker, or never sent);
- its current iteration has no job queued, started or retried: the phase's
  callback was lost, or found nothing to do;
- its current iteration has jobs queued, none started: their messages were lost;
- it has a started job too, and has been quiet for ``visibility_timeout`` more:
  the broker would have handed a lost worker's job to another worker by then,
  so the broker lost its copy (a restarted, empty Redis).

A run holding a started job, quiet for less than that, is a long job at
work and is left alone; so, for as long, is a run whose next work goes to
a queue that holds messages (``busy``: it may be waiting its turn). :func:`heal_run` sends a stalled run's current work
again through :func:`scheduler.stages.resume`'s code path (its jobs without
a result, then the phase's callback; a queued run's start) and records an
event line on the run saying why and what it sent; the event moves the
run's ``updated``, so the same run is healed at most once per
``heal_after``. Everything sent is idempotent (upserted jobs, a
compare-and-set step, :func:`scheduler.stages.catch_up`), so a run healed
while its work was only slow does that work twice at most. Workers run
:func:`heal` periodically (:mod:`workers.healer`); ``undream status`` shows
the same rule's verdicts.
"""
from __future__ import annotations

import datetime as dt
import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Collection

from undream.errors import StoreError

if TYPE_CHECKING:
    from scheduler.stages import Dispatch
    from undream.settings import Settings
    from undream.store import Store
    from undream.store.activity import RunHealth

log = logging.getLogger(__name__)

HEAL_BATCH = 50  # stalled runs one pass heals at most (quiet longest first); the next pass takes the rest


@dataclass(frozen=True)
class StallRule:
    """When a quiet farm run counts as stalled: ``after_s`` seconds without progress (0: never),
    ``started_s`` with a job started (the broker redelivers a lost worker's job before that)."""

    after_s: float
    started_s: float

    @classmethod
    def of(cls, settings: "Settings") -> "StallRule":
        """The rule of a farm's settings: ``heal_after``, and ``visibility_timeout`` more with a job started."""
        return cls(float(settings.heal_after), float(settings.heal_after + settings.visibility_timeout))


def _duration(seconds: float) -> str:
    s = int(seconds)
    return f"{s} s" if s < 120 else f"{s // 60} min" if s < 7200 else f"{s // 3600} h"


def waits_for(run: "RunHealth") -> str:
    """What the run's next work is, by the kinds of :meth:`undream.store.Store.stalled_runs`:
    ``queued`` (its start), ``jobs`` (its current iteration's jobs) or ``callback``."""
    if run.status == "queued":
        return "queued"
    return "jobs" if run.unfinished else "callback"


def stall_reason(run: "RunHealth", now: dt.datetime, rule: StallRule, busy: Collection[str] = ()) -> str | None:
    """Why the quiet farm run ``run`` is stalled, in one line; None when it is not: quiet for less
    than ``rule.after_s``; a started job, quiet for less than ``rule.started_s``; or its next work
    (:func:`waits_for`) is of a kind in ``busy``, whose queue holds messages: it may be waiting
    behind other runs' work (a sweep's starts, a long frames queue), not lost; but not for longer
    than ``rule.started_s``."""
    quiet = (now - (max(run.updated, run.last_job) if run.last_job else run.updated)).total_seconds()
    if rule.after_s <= 0 or quiet < rule.after_s:
        return None
    at, since = f"k={run.iteration}", _duration(quiet)
    if run.started and quiet >= rule.started_s:
        return f"{run.started} job(s) started at {at}, nothing finished for {since} (the broker lost them)"
    if run.started or (waits_for(run) in busy and quiet < rule.started_s):  # a long queue, for an hour at most
        return None
    if run.status == "queued":
        return f"queued, its start not run for {since}"
    if run.unfinished == 0:
        return f"no job queued or started at {at} for {since} (its callback lost, or it found nothing to do)"
    return f"{run.unfinished} job(s) queued at {at}, none started for {since} (their messages lost)"


def stalled(store: "Store", rule: StallRule, now: dt.datetime | None = None, limit: int = HEAL_BATCH,
            busy: Collection[str] = ()) -> list[tuple["RunHealth", str]]:
    """The stalled farm runs (at most ``limit``, quiet longest first), each with why (``busy``:
    see :func:`stall_reason`)."""
    if rule.after_s <= 0:
        return []
    now = now or dt.datetime.now(dt.timezone.utc)
    runs = store.quiet_runs(now - dt.timedelta(seconds=rule.after_s), limit)
    return [(run, why) for run in runs if (why := stall_reason(run, now, rule, busy)) is not None]


def heal_run(store: "Store", run_id: str, dispatch: "Dispatch", why: str, by: str) -> str:
    """Send the stalled run's current work again (:func:`scheduler.stages.resume`) and record an
    event line by ``by`` saying ``why`` and what was sent; returns the phase sent (or ``start``)."""
    from scheduler.stages import resume  # the stages load the attacks and outputs: not for `undream status`

    sent = resume(store, run_id, dispatch)
    store.add_event(run_id, f"healed: {why}; sent again: {_sent(sent)}", by)
    return sent


def _sent(phase: str) -> str:
    return "its start" if phase == "start" else f"its {phase} jobs without a result, then their callback"


def heal(store: "Store", dispatch: "Dispatch", rule: StallRule, by: str, now: dt.datetime | None = None,
         limit: int = HEAL_BATCH, busy: Collection[str] = ()) -> list[dict[str, Any]]:
    """One pass: heal every stalled run (at most ``limit``; ``busy``: see :func:`stall_reason`);
    returns what it did, a dict per run. A run the store cannot heal now (the database away a
    moment) is logged and left to the next pass."""
    healed = []
    for run, why in stalled(store, rule, now, limit, busy):
        try:
            sent = heal_run(store, run.id, dispatch, why, by)
        except StoreError as err:
            log.warning("run %s: stalled (%s) but not healed: %s", run.id, why, err)
            continue
        log.warning("run %s healed: %s; sent again: %s", run.id, why, _sent(sent))
        healed.append({"run_id": run.id, "reason": why, "sent": sent})
    return healed
