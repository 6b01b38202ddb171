"""A run's context rebuilt from its id, cached per process (least recently used dropped).

A worker process serves frame jobs of many runs; building a run's context
(unpacking the scene, loading its Mitsuba scenes and its victim) costs
seconds, a frame job tens of milliseconds. So each process keeps the
contexts of the last few runs it served. Every loaded Mitsuba scene slows
every later render of the process (docs/architecture.md), so a dropped
context closes its scenes.
"""
from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

from undream.errors import StoreError
from undream.spec.run import RunConfig

if TYPE_CHECKING:
    from undream.engine.context import RunContext
    from undream.store import RunSnapshot, Store


def run_config(run: "RunSnapshot") -> RunConfig:
    """The run's config as submitted."""
    return RunConfig.from_json(run.config)


def context_for_run(store: "Store", run: "RunSnapshot", cache_dir: Path | str) -> "RunContext":
    """Build the context of a submitted run: its scene from the blob store, then build_context."""
    from scheduler.scenes import unpack_scene
    from undream.engine.context import build_context

    if run.scene_ref is None:
        raise StoreError(f"run {run.id!r}: records no scene (was it made by `undream run`?)")
    return build_context(run_config(run), unpack_scene(store.blobs, run.scene_ref, cache_dir))


class ContextCache:
    """The contexts of the last ``size`` runs this process served, by run id."""

    def __init__(self, store: "Store", cache_dir: Path | str, size: int = 2) -> None:
        self.store = store
        self.cache_dir = Path(cache_dir)
        self.size = size
        self._contexts: OrderedDict[str, RunContext] = OrderedDict()
        self.built = 0  # contexts built so far (for tests and the benchmark)

    def __call__(self, run_id: str) -> "RunContext":
        ctx = self._contexts.get(run_id)
        if ctx is not None:
            self._contexts.move_to_end(run_id)
            return ctx
        ctx = context_for_run(self.store, self.store.get_run(run_id), self.cache_dir)
        self.built += 1
        self._contexts[run_id] = ctx
        while len(self._contexts) > self.size:
            _, old = self._contexts.popitem(last=False)
            old.scenes.close()
        return ctx

    def __contains__(self, run_id: str) -> bool:
        return run_id in self._contexts

    def clear(self) -> None:
        while self._contexts:
            _, old = self._contexts.popitem(last=False)
            old.scenes.close()
