"""``undream worker``: a prefork Celery worker on the farm's queues, Mitsuba only in its children."""
from __future__ import annotations

import logging
import os
import socket
import sys
import threading
from typing import TYPE_CHECKING, Any, Callable

from undream.redact import install_log_redaction
from workers.app import QUEUES, create_celery_app
from workers.healer import start_healer
from workers.presence import announce
from workers.runtime import drjit_threads_for, init_process

if TYPE_CHECKING:
    from undream.settings import Settings

log = logging.getLogger(__name__)
HEAVY = ("mitsuba", "drjit", "torch")  # never imported in the worker's parent process


def node_name(hostname: str | None = None) -> str:
    """The worker's Celery node name: ``hostname``, else ``undream-<pid>@<host>``."""
    return hostname or f"undream-{os.getpid()}@{socket.gethostname()}"


def worker_argv(settings: "Settings", loglevel: str = "INFO", hostname: str | None = None) -> list[str]:
    """The ``celery worker`` arguments of an undream worker."""
    name = node_name(hostname)
    return ["worker", "--pool=prefork", f"--concurrency={settings.concurrency}",
            f"--queues={','.join(QUEUES)}", f"--loglevel={loglevel}", f"--hostname={name}",
            "--without-gossip", "--without-mingle", "--without-heartbeat"]


def held_runs() -> list[str]:
    """The runs of the tasks this worker (its parent process) holds: running in a child, prefetched,
    or waiting out a retry's countdown (Celery's ``worker.state.requests``); a task's run is its
    first argument (the heal pass's is a node name, which names no run)."""
    from celery.worker import state

    return [req.args[0] for req in list(state.requests.values())
            if req.args and isinstance(req.args[0], str)]


def run_worker(settings: "Settings", loglevel: str = "INFO", hostname: str | None = None) -> None:
    """Run a worker until it is stopped (blocks). Every log record of the worker and of its child
    processes is redacted, at every level (:func:`undream.redact.install_log_redaction`): at
    ``--loglevel DEBUG`` botocore dumps each S3 request, and its ``Authorization`` header,
    signature, access key id and this worker's S3 keys are ``***`` in the log."""
    from celery import signals

    install_log_redaction((settings.s3_access_key_id, settings.s3_secret_access_key))
    app = create_celery_app(settings)
    node = node_name(hostname)
    withdraw: list[Callable[[], None]] = []
    nudge = threading.Event()  # a task arrived: announce what the worker holds now

    def _child_init(**_: Any) -> None:
        app.undream_local = init_process(settings, app.undream_local)  # type: ignore[attr-defined]

    def _ready(**_: Any) -> None:
        heavy = [m for m in HEAVY if m in sys.modules]
        if heavy:
            log.error("undream worker: %s imported in the worker's parent process (not fork-safe)", heavy)
        log.info("undream worker ready: %d process(es), %d Dr.Jit thread(s) each, parent without %s",
                 settings.concurrency, drjit_threads_for(settings), ", ".join(HEAVY))
        # `undream status` sees it live from now, and the healer the runs it holds
        withdraw.append(announce(settings, node, QUEUES, holds=held_runs, nudge=nudge))
        withdraw.append(start_healer(app, settings, node))  # stalled runs sent again, one worker at a time

    def _shutdown(**_: Any) -> None:
        for stop in withdraw:
            stop()

    signals.task_received.connect(lambda **_: nudge.set(), weak=False)
    signals.worker_process_init.connect(_child_init, weak=False)
    signals.worker_ready.connect(_ready, weak=False)
    signals.worker_shutdown.connect(_shutdown, weak=False)
    app.worker_main(worker_argv(settings, loglevel, node))
