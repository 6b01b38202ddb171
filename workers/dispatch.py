"""The stages' :class:`scheduler.stages.Dispatch` on Celery: a chord per phase of per-frame jobs."""
from __future__ import annotations

from typing import TYPE_CHECKING

from workers.queues import CONTROL_QUEUE, FRAMES_QUEUE

if TYPE_CHECKING:
    from celery import Celery


class CeleryDispatch:
    """Sends stage work to the farm: ``undream.start``, and chords of ``undream.frames`` →
    ``undream.collect`` (the callback reads the store, so it is immutable: no header results)."""

    def __init__(self, app: "Celery") -> None:
        self.app = app

    def start(self, run_id: str) -> None:
        self.app.signature("undream.start", args=(run_id,), queue=CONTROL_QUEUE).apply_async()

    def frames(self, run_id: str, phase: str, k: int, batches: list[list[int]]) -> None:
        from celery import chord

        body = self.app.signature("undream.collect", args=(run_id, phase, k), queue=CONTROL_QUEUE,
                                  immutable=True)
        if not batches:
            body.apply_async()
            return
        header = [self.app.signature("undream.frames", args=(run_id, phase, k, list(b)), queue=FRAMES_QUEUE)
                  for b in batches]
        chord(header, body, app=self.app).apply_async()
