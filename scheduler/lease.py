"""The stale-run rule: a run driven by one process is never left ``running`` after that process dies.

``undream run`` holds its run's lease (:class:`Lease`): the store records the
process as the run's owner (``host:pid``) and a thread refreshes the
heartbeat every ``BEAT_SECONDS``. A run is *stale* (:func:`stale_reason`)
when it is queued, running or evaluating, has an owner, and either

- the owner ran on this host and its process is gone (no such pid, or a
  zombie), or
- its heartbeat is older than ``LEASE_SECONDS`` (an owner on another host,
  or one frozen for that long).

:func:`expire_stale` fails stale runs with the reason (a compare-and-set
that loses to a heartbeat arriving meanwhile); ``undream status`` applies it
before it shows runs, and ``undream run --resume`` before it takes a run
over. Farm runs have no owner; the broker redelivers their lost jobs.
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import socket
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

from undream.errors import StoreError
from undream.store.leases import LIVE

if TYPE_CHECKING:
    from undream.store import RunSnapshot, Store

log = logging.getLogger(__name__)

BEAT_SECONDS = 5.0  # how often an owner refreshes its heartbeat
LEASE_SECONDS = 60.0  # a heartbeat older than this marks the run stale, wherever its owner ran


def this_process() -> str:
    """The owner name of this process: ``host:pid``."""
    return f"{socket.gethostname()}:{os.getpid()}"


def process_gone(pid: int) -> bool:
    """Whether no live process has ``pid`` on this host (a zombie counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # it exists, under another user
        return False
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rpartition(")")[2].split()[:1] == ["Z"]


def stale_reason(run: "RunSnapshot", now: dt.datetime, lease_s: float = LEASE_SECONDS) -> str | None:
    """Why ``run`` is stale (one line naming its owner), or None when it is not."""
    if run.status not in LIVE or run.owner is None:
        return None
    age = None if run.heartbeat is None else (now - run.heartbeat).total_seconds()
    since = "never" if age is None else f"{age:.0f} s ago"
    host, _, pid = run.owner.rpartition(":")
    if host == socket.gethostname() and pid.isdigit() and process_gone(int(pid)):
        return (f"the process that ran it ({run.owner}) is gone (last heartbeat {since}); "
                "continue it with `undream run ... --resume`")
    if age is None or age > lease_s:
        return (f"the process that ran it ({run.owner}) stopped: no heartbeat for "
                f"{since.removesuffix(' ago')} (lease {lease_s:.0f} s); continue it with `undream run ... --resume`")
    return None


def expire_stale(store: "Store", runs: Iterable["RunSnapshot"] | None = None,
                 lease_s: float = LEASE_SECONDS) -> list[str]:
    """Fail every stale run (of ``runs``, default every owned live run) with its reason; returns their ids."""
    from undream.store.models import utcnow

    now = utcnow()
    expired = []
    for run in store.owned_runs() if runs is None else runs:
        reason = stale_reason(run, now, lease_s)
        if reason is not None and store.expire(run.id, run.owner, now, reason):  # type: ignore[arg-type]
            log.warning("run %s marked failed: %s", run.id, reason)
            expired.append(run.id)
    return expired


class Lease:
    """Hold a run's lease while a block runs: claim, heartbeat thread, release.

    ``with Lease(store, run_id):`` raises StoreError when another live
    process holds the run. A heartbeat that finds the lease lost (another
    process judged this one stale) logs it once; the run's compare-and-set
    steps refuse to move a run that is no longer active.
    """

    def __init__(self, store: "Store", run_id: str, owner: str | None = None,
                 beat_s: float = BEAT_SECONDS) -> None:
        self.store, self.run_id = store, run_id
        self.owner = owner or this_process()
        self.beat_s = beat_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> "Lease":
        if not self.store.claim(self.run_id, self.owner):
            holder = self.store.get_run(self.run_id)
            raise StoreError(f"run {self.run_id}: being run by {holder.owner} (status {holder.status}); "
                             "wait for it, or stop that process first")
        self._thread = threading.Thread(target=self._beat, name=f"lease-{self.run_id[:8]}", daemon=True)
        self._thread.start()
        return self

    def _beat(self) -> None:
        warned = False
        while not self._stop.wait(self.beat_s):
            try:
                held = self.store.beat(self.run_id, self.owner)
            except StoreError as exc:  # a database hiccup: try again at the next beat
                log.warning("run %s: heartbeat failed: %s", self.run_id, exc)
                continue
            if not held and not warned:
                log.warning("run %s: lease lost (another process marked this one stale)", self.run_id)
                warned = True

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        try:
            self.store.release(self.run_id, self.owner)
        except StoreError as err:
            log.warning("run %s: could not release its lease: %s", self.run_id, err)
