"""Workers heal the farm's runs by themselves: one heal pass per ``heal_interval``, farm-wide.

Each ``undream worker``'s parent process runs a daemon thread (:func:`start_healer`) that, every
``heal_interval`` seconds, tries to take the farm's heal lease: the key :data:`LEASE_KEY` in the
result backend's Redis, set only where absent (``SET NX``) and expiring after the interval. The
worker holding it sends one ``undream.heal`` task to the control queue, and a child process runs
it (:func:`scheduler.heal.heal` with the child's store and dispatch: the stalled runs' current work
sent again, an event line on each). So however many workers there are, one pass runs per
interval; a worker killed while it holds the lease loses it at the expiry. The parent opens no
database (engines are not fork-safe) and imports no renderer; a pass is bounded
(:data:`scheduler.heal.HEAL_BATCH` runs) and skipped once its interval is over (the task expires).
``heal_after`` 0 turns healing off.
"""
from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Callable

import redis  # comes with celery[redis]

from workers.queues import CONTROL_QUEUE

if TYPE_CHECKING:
    from celery import Celery

    from undream.settings import Settings

log = logging.getLogger(__name__)

LEASE_KEY = "undream:heal"  # held by the worker that sends this interval's heal pass (its node name)
HEAL_TASK = "undream.heal"


def take_lease(client: redis.Redis, node: str, ttl_s: int) -> bool:
    """Take the farm's heal lease for ``ttl_s`` seconds if nobody holds it; True if ``node`` took it."""
    return bool(client.set(LEASE_KEY, node, nx=True, ex=max(1, ttl_s)))


def start_healer(app: "Celery", settings: "Settings", node: str) -> Callable[[], None]:
    """Every ``heal_interval`` s, from a daemon thread: take the lease and, holding it, send one
    ``undream.heal`` task. Returns the function that stops it. A broker away a moment is a log
    line and a try at the next interval; ``heal_after`` 0: nothing starts."""
    if settings.heal_after <= 0:
        return lambda: None
    client = redis.Redis.from_url(settings.backend_url, socket_connect_timeout=settings.connect_timeout,
                                  socket_timeout=settings.connect_timeout)
    stop, interval = threading.Event(), settings.heal_interval

    def tick() -> None:
        try:
            if take_lease(client, node, interval):
                app.signature(HEAL_TASK, args=(node,), queue=CONTROL_QUEUE).apply_async(expires=interval)
        except Exception as exc:  # redis-py's or kombu's connection errors
            log.warning("worker %s: heal check not sent: %s", node, " ".join(str(exc).split()))

    def loop() -> None:
        while not stop.wait(interval):
            tick()

    thread = threading.Thread(target=loop, name="undream-healer", daemon=True)
    thread.start()

    def halt() -> None:
        stop.set()
        thread.join(5)
        client.close()

    return halt
