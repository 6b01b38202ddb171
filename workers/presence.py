"""Live workers say so in Redis: a key per worker that lapses when the worker stops saying it.

Each ``undream worker`` (its parent process, from the moment it is ready)
sets ``undream:worker:<node name>`` in the result backend's Redis (always
Redis: see :class:`undream.settings.Settings`) every ``worker_beat`` seconds (the
setting, 10 by default), holding the queues it consumes, with an expiry of three
beats (:func:`ttl_of`); it deletes
the key when it shuts down. :func:`live_queues` reads every such key in one
round trip or two, so a command learns which queues have a live consumer in
milliseconds, where Celery's remote control (``inspect().active_queues()``)
waits its whole timeout for answers however many workers there are. A worker
killed with SIGKILL stays listed until its key expires (at most three beats).

An announcement also names the runs of the tasks the worker holds (running,
prefetched, or waiting out a retry's countdown: Celery's ``worker.state``
requests in the parent process), and a task's arrival wakes the announcing
thread, so a task taken is announced within :data:`NUDGE_S`. The healer
(:mod:`scheduler.heal`) never sends again the work of a run a live worker
holds. Its absence from every announcement means something only once every
live worker has announced itself since Redis last started empty: each
announcement also sets :data:`SINCE_KEY` where absent (no expiry), and
:func:`presence` calls the announcements complete once that key is
three beats old.
"""
from __future__ import annotations

import base64
import json
import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterable, Sequence

import redis  # comes with celery[redis]

if TYPE_CHECKING:
    from undream.settings import Settings

log = logging.getLogger(__name__)

PREFIX = "undream:worker:"
# kombu's Redis transport keeps a queue as one list per priority step: the name, then name + SEP + step
PRIORITY_SEP, PRIORITY_STEPS = "\x06\x16", (0, 3, 6, 9)
BEATS_TO_LAPSE = 3  # a key outlives its last announcement by this many beats: a worker silent so long is not live
NUDGE_S = 1.0  # s at least between two announcements (a task's arrival announces at once, then waits this)
SINCE_KEY = "undream:presence:since"  # when the first announcement since Redis started empty was made (epoch s)


def ttl_of(settings: "Settings") -> float:
    """Seconds an announcement outlives its worker's last beat (three ``worker_beat``): a worker
    silent this long is not live."""
    return float(BEATS_TO_LAPSE * settings.worker_beat)


def _client(settings: "Settings") -> redis.Redis:
    return redis.Redis.from_url(settings.backend_url, socket_connect_timeout=settings.connect_timeout,
                                socket_timeout=settings.connect_timeout)


def announce(settings: "Settings", node: str, queues: Sequence[str], beat_s: float | None = None,
             ttl_s: float | None = None, holds: Callable[[], Iterable[str]] = tuple,
             nudge: threading.Event | None = None) -> Callable[[], None]:
    """Announce worker ``node`` as consuming ``queues`` and holding tasks of the runs ``holds()``
    now and every ``beat_s`` seconds (None: the ``worker_beat`` setting; ``ttl_s`` None: three of
    them), and at once (``NUDGE_S`` apart at most) when ``nudge`` is
    set, from a daemon thread; returns the function that stops announcing and deletes the key. A
    failed announcement (Redis away a moment) is logged and tried again at the next beat."""
    beat_s = float(settings.worker_beat) if beat_s is None else beat_s
    ttl_s = ttl_of(settings) if ttl_s is None else ttl_s
    client, key, stop = _client(settings), PREFIX + node, threading.Event()
    woken = nudge or threading.Event()

    def say() -> None:
        try:
            runs = sorted(set(holds()))
            value = json.dumps({"node": node, "queues": list(queues), "runs": runs, "at": time.time()})
            with client.pipeline(transaction=False) as pipe:
                pipe.set(key, value, ex=max(1, round(ttl_s)))
                pipe.set(SINCE_KEY, time.time(), nx=True)
                pipe.execute()
        except Exception as exc:  # redis-py's ConnectionError and friends; a dict changed while read
            log.warning("worker %s: cannot announce itself in Redis: %s", node, exc)

    def beat() -> None:
        while not stop.is_set():
            nudged = woken.wait(beat_s)
            woken.clear()
            if stop.is_set():
                return
            say()
            if nudged:
                stop.wait(NUDGE_S)

    say()  # live when this returns
    thread = threading.Thread(target=beat, name="undream-presence", daemon=True)
    thread.start()

    def withdraw() -> None:
        stop.set()
        woken.set()
        thread.join(5)
        try:
            client.delete(key)
        except Exception as exc:
            log.warning("worker %s: cannot withdraw its announcement: %s", node, exc)

    return withdraw


@dataclass(frozen=True)
class Presence:
    """The live workers' announcements: queue → the nodes consuming it; ``runs``: the runs whose
    tasks they hold; ``complete``: every live worker has announced itself since Redis last started
    empty (:data:`SINCE_KEY` at least :func:`ttl_of` old), so a run in no announcement is held by none."""

    queues: dict[str, tuple[str, ...]]
    runs: frozenset[str]
    complete: bool


def presence(settings: "Settings", now: float | None = None) -> Presence:
    """The announcements, read in two round trips; raises redis-py's errors when Redis cannot be
    reached (the caller says so)."""
    client = _client(settings)
    try:
        keys = sorted(client.scan_iter(match=PREFIX + "*", count=1000))
        values = client.mget(keys) if keys else []
        since = client.get(SINCE_KEY)
    finally:
        client.close()
    queues: dict[str, list[str]] = {}
    runs: set[str] = set()
    for raw in values:
        if raw is None:  # expired between the scan and the read
            continue
        try:
            entry = json.loads(raw)
            node, consumed = str(entry["node"]), [str(q) for q in entry["queues"]]
            held = [str(r) for r in entry.get("runs", ())]
        except (ValueError, KeyError, TypeError, AttributeError):
            continue
        runs.update(held)
        for queue in consumed:
            queues.setdefault(queue, []).append(node)
    try:
        age = (time.time() if now is None else now) - float(since) if since is not None else -1.0
    except ValueError:
        age = -1.0
    return Presence({q: tuple(sorted(nodes)) for q, nodes in sorted(queues.items())}, frozenset(runs),
                    age >= ttl_of(settings))


def live_queues(settings: "Settings") -> dict[str, tuple[str, ...]]:
    """Queue → the live workers (node names) consuming it, from their announcements; raises
    redis-py's errors when Redis cannot be reached (the caller says so)."""
    return presence(settings).queues


SCAN_LIMIT = 20_000  # messages of one queue read to learn which runs wait there; a longer queue is not read


def queued_runs(settings: "Settings", queues: Sequence[str],
                limit: int = SCAN_LIMIT) -> tuple[frozenset[str], frozenset[str]]:
    """The runs with a message waiting in ``queues`` (every priority's list) and the queues not
    read (longer than ``limit`` messages); raises redis-py's errors when Redis cannot be reached.
    A message's run is its task's first argument (every undream task but the heal pass has one)."""
    client = redis.Redis.from_url(settings.broker_url, socket_connect_timeout=settings.connect_timeout,
                                  socket_timeout=settings.connect_timeout)
    lists = {q: [f"{q}{PRIORITY_SEP}{step}" if step else q for step in PRIORITY_STEPS] for q in queues}
    runs: set[str] = set()
    unread = set()
    try:
        with client.pipeline() as pipe:
            for names in lists.values():
                for name in names:
                    pipe.llen(name)
            sizes = iter(pipe.execute())
        readable = []
        for queue, names in lists.items():
            if sum(next(sizes) for _ in names) > limit:
                unread.add(queue)
            else:
                readable.append(queue)
        with client.pipeline() as pipe:
            for queue in readable:
                for name in lists[queue]:
                    pipe.lrange(name, 0, limit)
            messages = [m for batch in pipe.execute() for m in batch]
    finally:
        client.close()
    runs.update(filter(None, map(message_run, messages)))
    return frozenset(runs), frozenset(unread)


def message_run(raw: bytes) -> str | None:
    """The run id of a task message as kombu's Redis transport keeps it (JSON whose ``body`` is the
    base64 of Celery's ``[args, kwargs, embed]``): its first argument; None for another message."""
    try:
        message = json.loads(raw)
        body = message["body"]
        if message.get("properties", {}).get("body_encoding") == "base64":
            body = base64.b64decode(body)
        args = json.loads(body)[0]
        return args[0] if args and isinstance(args[0], str) else None
    except (ValueError, KeyError, IndexError, TypeError, AttributeError):
        return None
