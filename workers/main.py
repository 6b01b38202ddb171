"""``undream worker``: a prefork Celery worker on the farm's queues, Mitsuba only in its children."""
from __future__ import annotations

import logging
import os
import socket
import sys
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

    def _child_init(**_: Any) -> None:
        app.undream_local = init_process(settings, app.undream_local)  # type: ignore[attr-defined]

    def _ready(**_: Any) -> None:
        heavy = [m for m in HEAVY if m in sys.modules]
        if heavy:
            log.error("undream worker: %s imported in the worker's parent process (not fork-safe)", heavy)
        log.info("undream worker ready: %d process(es), %d Dr.Jit thread(s) each, parent without %s",
                 settings.concurrency, drjit_threads_for(settings), ", ".join(HEAVY))
        withdraw.append(announce(settings, node, QUEUES))  # `undream status` sees it live from now
        withdraw.append(start_healer(app, settings, node))  # stalled runs sent again, one worker at a time

    def _shutdown(**_: Any) -> None:
        for stop in withdraw:
            stop()

    signals.worker_process_init.connect(_child_init, weak=False)
    signals.worker_ready.connect(_ready, weak=False)
    signals.worker_shutdown.connect(_shutdown, weak=False)
    app.worker_main(worker_argv(settings, loglevel, node))
