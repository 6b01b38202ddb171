"""Runs heal: a farm run that makes no progress has its current work sent again, by the farm.

The stall rule (:func:`stall_reason`) looks at the farm's active runs in
which nothing happened for ``heal_after`` seconds (the run's row unchanged,
no job of its current iteration started or finished since:
:meth:`undream.store.Store.quiet_runs`), and asks the broker what it knows of
each (a :class:`FarmView`, :func:`workers.health.farm_view`):

- **held**: a live worker holds a task of the run (running it, prefetched, or
  waiting out a retry's countdown): each ``undream worker`` names the runs of
  the tasks it holds in its announcement (:mod:`workers.presence`). Such a
  run is at work, however long its job takes, and is never sent again;
- **waiting**: a message of the run sits in one of the broker's queues: it
  is waiting its turn behind other runs' work, not lost.

A quiet run neither held nor waiting is *stalled*: its start, its jobs or its
callback are nowhere (lost with a restarted broker, or with a worker that was
killed or stopped: its announcement lapses three ``worker_beat`` after its
last, :func:`workers.presence.ttl_of`), or its callback found nothing to do. Where the broker cannot
say (its Redis unreachable, restarted less than those three beats ago so that not
every worker has announced itself again, or a queue too long to read), the
rule falls back on time alone: a run is stalled only after ``visibility_timeout``
more (the broker would have delivered a lost worker's job again by then).

:func:`heal` confirms each verdict with a second look :data:`CONFIRM_S` later
(an announcement trails a delivery by up to a second), then :func:`heal_run`
sends the run's current work again through :func:`scheduler.stages.resume`'s
code path (its jobs without a result, then the phase's callback; a queued
run's start), keeping the jobs' attempts (a job that kills its worker each
time still gives up at ``max_attempts``), and records an event line on the
run saying why and what it sent. The event moves the run's ``updated``, so
one run is healed at most once per ``heal_after``. Everything sent is
idempotent (upserted jobs, a compare-and-set step, :func:`scheduler.stages.catch_up`).
Workers run :func:`heal` periodically (:mod:`workers.healer`); ``undream
status`` shows the same rule's verdicts.
"""
from __future__ import annotations

import datetime as dt
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from undream.errors import StoreError

if TYPE_CHECKING:
    from scheduler.stages import Dispatch
    from undream.settings import Settings
    from undream.store import Store
    from undream.store.activity import RunHealth

log = logging.getLogger(__name__)

HEAL_BATCH = 50  # stalled runs one pass heals at most (quiet longest first); the next pass takes the rest
QUIET_SCAN = 1000  # quiet runs a look reads (quiet longest first): runs waiting in a queue are quiet too
CONFIRM_S = 2.0  # s between a pass's two looks at the broker (a worker announces a task it took within 1 s)


@dataclass(frozen=True)
class StallRule:
    """When a quiet farm run counts as stalled: ``after_s`` seconds without progress (0: never);
    where the broker cannot say what holds the run, ``started_s`` (the broker redelivers a lost
    worker's job before that)."""

    after_s: float
    started_s: float

    @classmethod
    def of(cls, settings: "Settings") -> "StallRule":
        """The rule of a farm's settings: ``heal_after``, and ``visibility_timeout`` more when blind."""
        return cls(float(settings.heal_after), float(settings.heal_after + settings.visibility_timeout))


@dataclass(frozen=True)
class FarmView:
    """What the broker says of the farm's runs now (:func:`workers.health.farm_view`).

    ``held``: the runs a live worker holds a task of (None: unknown: the announcements unreadable,
    or not yet every worker's after a restarted Redis); ``waiting``: the runs with a message in a
    queue that was read; ``unread``: the kinds of next work (:func:`waits_for`) whose queue could
    not be read (unreachable, or too long), which may be waiting there; ``why``: why it is partial."""

    held: frozenset[str] | None = None
    waiting: frozenset[str] = frozenset()
    unread: frozenset[str] = frozenset({"queued", "callback", "jobs"})
    why: str = ""

    @classmethod
    def blind(cls, why: str = "") -> "FarmView":
        """Nothing known: the rule falls back on time alone."""
        return cls(why=why)


BLIND = FarmView.blind()


def _duration(seconds: float) -> str:
    s = int(seconds)
    return f"{s} s" if s < 120 else f"{s // 60} min" if s < 7200 else f"{s // 3600} h"


def waits_for(run: "RunHealth") -> str:
    """What the run's next work is, by the kinds of :meth:`undream.store.Store.stalled_runs`:
    ``queued`` (its start), ``jobs`` (its current iteration's jobs) or ``callback``."""
    if run.status == "queued":
        return "queued"
    return "jobs" if run.unfinished else "callback"


def stall_reason(run: "RunHealth", now: dt.datetime, rule: StallRule, view: FarmView = BLIND) -> str | None:
    """Why the quiet farm run ``run`` is stalled, in one line; None when it is not: quiet for less
    than ``rule.after_s``; a live worker holds a task of it (``view.held``); a message of it waits
    in a queue (``view.waiting``); or, where ``view`` cannot say (who holds what unknown, or its
    next work's queue unread: ``view.unread``), quiet for less than ``rule.started_s``."""
    quiet = (now - (max(run.updated, run.last_job) if run.last_job else run.updated)).total_seconds()
    if rule.after_s <= 0 or quiet < rule.after_s:
        return None
    if (view.held is not None and run.id in view.held) or run.id in view.waiting:
        return None
    at, since, blind = f"k={run.iteration}", _duration(quiet), quiet < rule.started_s
    if blind and (view.held is None or waits_for(run) in view.unread):
        return None  # a worker may hold it, or it may wait its turn: time alone decides, an hour on
    if run.started:
        holder = "no live worker holds them" if view.held is not None else "the broker lost them"
        return f"{run.started} job(s) started at {at}, nothing finished for {since} ({holder})"
    if run.status == "queued":
        return f"queued, its start not run for {since} (its message lost)"
    if run.unfinished == 0:
        return f"no job queued or started at {at} for {since} (its callback lost, or it found nothing to do)"
    return f"{run.unfinished} job(s) queued at {at}, none started for {since} (their messages lost)"


def stalled(store: "Store", rule: StallRule, now: dt.datetime | None = None, limit: int = HEAL_BATCH,
            view: FarmView = BLIND) -> list[tuple["RunHealth", str]]:
    """The stalled farm runs (at most ``limit``, quiet longest first), each with why (``view``:
    see :func:`stall_reason`), among the :data:`QUIET_SCAN` runs quiet longest (a sweep's runs
    waiting their turn in a queue are quiet too, and must not hide the stalled ones behind them)."""
    if rule.after_s <= 0:
        return []
    now = now or dt.datetime.now(dt.timezone.utc)
    runs = store.quiet_runs(now - dt.timedelta(seconds=rule.after_s), max(limit, QUIET_SCAN))
    return [(run, why) for run in runs if (why := stall_reason(run, now, rule, view)) is not None][:limit]


def heal_run(store: "Store", run_id: str, dispatch: "Dispatch", why: str, by: str) -> str:
    """Send the stalled run's current work again (:func:`scheduler.stages.resume`, the jobs'
    attempts kept) and record an event line by ``by`` saying ``why`` and what was sent; returns
    the phase sent (or ``start``)."""
    from scheduler.stages import resume  # the stages load the attacks and outputs: not for `undream status`

    sent = resume(store, run_id, dispatch, keep_attempts=True)
    store.add_event(run_id, f"healed: {why}; sent again: {_sent(sent)}", by)
    return sent


def _sent(phase: str) -> str:
    return "its start" if phase == "start" else f"its {phase} jobs without a result, then their callback"


def heal(store: "Store", dispatch: "Dispatch", rule: StallRule, by: str, now: dt.datetime | None = None,
         limit: int = HEAL_BATCH, view: Callable[[], FarmView] = lambda: BLIND,
         confirm_s: float = CONFIRM_S) -> list[dict[str, Any]]:
    """One pass: heal every stalled run (at most ``limit``), each found stalled by two looks
    ``confirm_s`` apart (``view``: the broker's answer, asked at each look; see :func:`stall_reason`);
    returns what it did, a dict per run. A run the store cannot heal now (the database away a
    moment) is logged and left to the next pass."""
    first = {run.id for run, _ in stalled(store, rule, now, limit, view())}
    if not first:
        return []
    if confirm_s > 0:
        time.sleep(confirm_s)
    healed = []
    later = None if now is None else now + dt.timedelta(seconds=confirm_s)
    for run, why in stalled(store, rule, later, limit, view()):
        if run.id not in first:
            continue
        try:
            sent = heal_run(store, run.id, dispatch, why, by)
        except StoreError as err:
            log.warning("run %s: stalled (%s) but not healed: %s", run.id, why, err)
            continue
        log.warning("run %s healed: %s; sent again: %s", run.id, why, _sent(sent))
        healed.append({"run_id": run.id, "reason": why, "sent": sent})
    return healed
