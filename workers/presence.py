"""Live workers say so in Redis: a key per worker that lapses when the worker stops saying it.

Each ``undream worker`` (its parent process, from the moment it is ready)
sets ``undream:worker:<node name>`` in the result backend's Redis (always
Redis: see :class:`undream.settings.Settings`) every :data:`BEAT_S` seconds,
holding the queues it consumes, with an expiry of :data:`TTL_S`; it deletes
the key when it shuts down. :func:`live_queues` reads every such key in one
round trip or two, so a command learns which queues have a live consumer in
milliseconds, where Celery's remote control (``inspect().active_queues()``)
waits its whole timeout for answers however many workers there are. A worker
killed with SIGKILL stays listed until its key expires (at most ``TTL_S``).
"""
from __future__ import annotations

import json
import logging
import threading
from typing import TYPE_CHECKING, Callable, Sequence

import redis  # comes with celery[redis]

if TYPE_CHECKING:
    from undream.settings import Settings

log = logging.getLogger(__name__)

PREFIX = "undream:worker:"
# kombu's Redis transport keeps a queue as one list per priority step: the name, then name + SEP + step
PRIORITY_SEP, PRIORITY_STEPS = "\x06\x16", (0, 3, 6, 9)
BEAT_S = 10.0  # s between a worker's announcements
TTL_S = 3 * BEAT_S  # s a key outlives its last announcement: a worker silent this long is not live


def _client(settings: "Settings") -> redis.Redis:
    return redis.Redis.from_url(settings.backend_url, socket_connect_timeout=settings.connect_timeout,
                                socket_timeout=settings.connect_timeout)


def announce(settings: "Settings", node: str, queues: Sequence[str], beat_s: float = BEAT_S,
             ttl_s: float = TTL_S) -> Callable[[], None]:
    """Announce worker ``node`` as consuming ``queues`` now and every ``beat_s`` seconds, from a
    daemon thread; returns the function that stops announcing and deletes the key. A failed
    announcement (Redis away a moment) is logged and tried again at the next beat."""
    client, key, stop = _client(settings), PREFIX + node, threading.Event()
    value = json.dumps({"node": node, "queues": list(queues)})

    def say() -> None:
        try:
            client.set(key, value, ex=max(1, round(ttl_s)))
        except Exception as exc:  # redis-py's ConnectionError and friends
            log.warning("worker %s: cannot announce itself in Redis: %s", node, exc)

    def beat() -> None:
        while not stop.wait(beat_s):
            say()

    say()  # live when this returns
    thread = threading.Thread(target=beat, name="undream-presence", daemon=True)
    thread.start()

    def withdraw() -> None:
        stop.set()
        thread.join(5)
        try:
            client.delete(key)
        except Exception as exc:
            log.warning("worker %s: cannot withdraw its announcement: %s", node, exc)

    return withdraw


def live_queues(settings: "Settings") -> dict[str, tuple[str, ...]]:
    """Queue → the live workers (node names) consuming it, from their announcements; raises
    redis-py's errors when Redis cannot be reached (the caller says so)."""
    client = _client(settings)
    try:
        keys = sorted(client.scan_iter(match=PREFIX + "*", count=1000))
        values = client.mget(keys) if keys else []
    finally:
        client.close()
    queues: dict[str, list[str]] = {}
    for raw in values:
        if raw is None:  # expired between the scan and the read
            continue
        try:
            entry = json.loads(raw)
            node, consumed = str(entry["node"]), [str(q) for q in entry["queues"]]
        except (ValueError, KeyError, TypeError):
            continue
        for queue in consumed:
            queues.setdefault(queue, []).append(node)
    return {q: tuple(sorted(nodes)) for q, nodes in sorted(queues.items())}


def queue_backlog(settings: "Settings", queues: Sequence[str]) -> dict[str, int]:
    """Queue → the messages waiting on it in the broker's Redis (every priority's list, one round
    trip); raises redis-py's errors when Redis cannot be reached."""
    client = redis.Redis.from_url(settings.broker_url, socket_connect_timeout=settings.connect_timeout,
                                  socket_timeout=settings.connect_timeout)
    try:
        with client.pipeline() as pipe:
            for queue in queues:
                for step in PRIORITY_STEPS:
                    pipe.llen(f"{queue}{PRIORITY_SEP}{step}" if step else queue)
            sizes = pipe.execute()
    finally:
        client.close()
    n = len(PRIORITY_STEPS)
    return {queue: int(sum(sizes[i * n:(i + 1) * n])) for i, queue in enumerate(queues)}
