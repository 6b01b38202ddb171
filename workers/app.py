"""The Celery app factory: one app per settings object, nothing built at import.

Farm rules (README, "Farm"; ../shared/DESIGN.md): JSON only on the wire (arrays
travel through the blob store as keys); a Redis result backend (chords need
one; never rpc); ``acks_late`` with ``reject_on_worker_lost`` and prefetch 1,
so a job whose worker dies goes back to the queue; a visibility timeout
longer than the longest job, after which Redis delivers a job of a worker
that vanished to another one. Two queues: ``undream.control`` (start and
the phase callbacks, short) before ``undream.frames`` (per-frame batches), so
a finished phase's callback never waits behind other runs' frames. Workers
send task events (and clients a ``task-sent`` event), so Flower, or
``celery events``, can watch the same farm.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from undream.errors import UndreamError
from undream.settings import load_local
from undream.store import mask_url
from workers.queues import CONTROL_QUEUE, FRAMES_QUEUE, QUEUES
from workers.tasks import register_tasks

PROCESS_START_TIMEOUT = 120.0  # seconds a worker child may take to start (Celery's worker_proc_alive_timeout)

if TYPE_CHECKING:
    from celery import Celery

    from undream.settings import LocalSettings, Settings

__all__ = ["BrokerError", "CONTROL_QUEUE", "FRAMES_QUEUE", "QUEUES", "check_reachable", "create_celery_app"]


class BrokerError(UndreamError):
    """The broker or the result backend cannot be reached."""


def create_celery_app(settings: "Settings", local: "LocalSettings | None" = None) -> "Celery":
    """A Celery app on ``settings``' broker and result backend, with undream's tasks registered.

    ``local``: the settings of the processes that run its tasks (None: read from the environment
    now, :func:`undream.settings.load_local`), kept as ``app.undream_local`` for :mod:`workers.runtime`.
    """
    from celery import Celery

    app = Celery("undream", broker=settings.broker_url, backend=settings.backend_url, set_as_current=False)
    transport = {
        "visibility_timeout": settings.visibility_timeout,
        "queue_order_strategy": "priority",  # control before frames, every poll
        "unacked_restore_interval": settings.restore_interval,
        "unacked_restore_throttle": 1,
        "socket_connect_timeout": settings.connect_timeout,
    }
    app.conf.update(
        task_serializer="json", result_serializer="json", accept_content=["json"],
        result_accept_content=["json"], event_serializer="json",
        task_acks_late=True, task_reject_on_worker_lost=True, worker_prefetch_multiplier=1,
        task_acks_on_failure_or_timeout=True,
        broker_transport_options=transport, result_backend_transport_options=dict(transport),
        broker_connection_retry_on_startup=True, broker_connection_max_retries=None,
        worker_cancel_long_running_tasks_on_connection_loss=True,
        result_backend_always_retry=True, result_backend_max_retries=10,
        result_expires=7 * 24 * 3600, result_extended=False,
        task_default_queue=FRAMES_QUEUE,
        task_routes={"undream.frames": {"queue": FRAMES_QUEUE},
                     "undream.start": {"queue": CONTROL_QUEUE},
                     "undream.collect": {"queue": CONTROL_QUEUE},
                     "undream.heal": {"queue": CONTROL_QUEUE}},
        worker_send_task_events=True, task_send_sent_event=True,  # task events: Flower can watch the farm
        # A child's start (workers.runtime.init_process: Mitsuba, torch, the victims' code warmed up)
        # takes seconds, more on a loaded machine; Celery's default 4 s killed children in a loop.
        worker_proc_alive_timeout=PROCESS_START_TIMEOUT,
    )
    app.undream_settings = settings  # type: ignore[attr-defined]  # read by workers.runtime
    app.undream_local = load_local() if local is None else local  # type: ignore[attr-defined]
    register_tasks(app)
    return app


def check_reachable(app: "Celery", settings: "Settings") -> None:
    """Connect to the broker and the result backend once; BrokerError naming the URL when not."""
    try:
        with app.connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, interval_start=0, interval_step=0,
                                   timeout=settings.connect_timeout)
    except Exception as exc:  # kombu raises OperationalError or the transport's own errors
        raise BrokerError(f"cannot reach the broker at {mask_url(settings.broker_url)!r}: "
                          f"{_reason(exc)}") from None
    try:
        app.backend.client.ping()
    except Exception as exc:
        raise BrokerError(f"cannot reach the result backend at {mask_url(settings.backend_url)!r}: "
                          f"{_reason(exc)}") from None


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text
