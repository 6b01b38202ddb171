"""A run's context rebuilt from its id, cached per process, sharing scenes and victims across runs.

A worker process serves frame jobs of many runs, interleaved (one iteration
of each active run in turn). Building a context from nothing (unpacking the
scene, loading its Mitsuba scenes and its victim) costs seconds, a frame job
tens of milliseconds, so each process keeps three least-recently-used caches:

- Mitsuba scene caches by scene directory (``scenes``, default 2): every
  loaded Mitsuba scene slows every later render of the process
  (docs/architecture.md), so few, and a dropped one is closed together with
  the contexts that use it;
- victims by (model, device, task) (``victims``, default 4);
- the runs' own contexts by run id (``runs``, default 32): config, targets,
  attack, gradient path — cheap once the scene and victim are loaded.

The runs of a sweep over attack settings share one scene and one victim, so
a worker serving all of them loads each once.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from scheduler.transports import DEFAULT_CACHE_MB, BlobTransportShelf
from undream.errors import StoreError
from undream.lru import LRU
from undream.render.scene_cache import SceneCache
from undream.settings import LocalSettings
from undream.spec.run import RunConfig

if TYPE_CHECKING:
    from undream.engine.context import RunContext
    from undream.store import RunSnapshot, Store


class ContextCache:
    """Contexts of the runs this process serves, by run id (see the module docstring)."""

    def __init__(self, store: "Store", cache_dir: Path | str, scenes: int = 2, victims: int = 4,
                 runs: int = 32, local: LocalSettings = LocalSettings(),
                 transport_cache_mb: int = DEFAULT_CACHE_MB) -> None:
        self.store = store
        self.transport_cache_bytes = transport_cache_mb << 20  # the blob store's transport cache cap
        self.local = local  # this process's settings, read at the edge (the worker's start)
        self.cache_dir = Path(cache_dir)
        self._scenes: LRU[Path, Any] = LRU(scenes, on_evict=self._drop_scenes)
        self._victims: LRU[tuple[Any, ...], Any] = LRU(victims)
        self._contexts: LRU[str, "RunContext"] = LRU(runs)
        self.built = {"contexts": 0, "scenes": 0, "victims": 0}  # loads so far (tests, benchmark)

    def __call__(self, run_id: str) -> "RunContext":
        if run_id in self._contexts:
            ctx = self._contexts.touch(run_id)
            self._scenes.touch(ctx.scene_dir)
            return ctx
        from scheduler.scenes import unpack_scene
        from undream.engine.context import build_context, task_of

        run = self.store.get_run(run_id)
        if run.scene_ref is None:
            raise StoreError(f"run {run_id!r}: records no scene (was it made by `undream run`?)")
        config = run.run_config
        scene_dir = unpack_scene(self.store.blobs, run.scene_ref, self.cache_dir)
        ctx = build_context(config, scene_dir, victim=self._victim(config, task_of(config)),
                            scenes=self._scene_cache(scene_dir), local=self.local)
        ctx.gradients.shelf = BlobTransportShelf(self.store.blobs, run.scene_ref,
                                                  self.transport_cache_bytes)
        self.built["contexts"] += 1
        return self._contexts.put(run_id, ctx)

    def _scene_cache(self, scene_dir: Path) -> Any:
        if scene_dir in self._scenes:
            return self._scenes.touch(scene_dir)
        scenes = SceneCache(scene_dir, frozen=self.local.frozen)
        self.built["scenes"] += 1
        return self._scenes.put(scene_dir, scenes)

    def _drop_scenes(self, scene_dir: Path, old: Any) -> None:
        """A scene cache dropped: the contexts that use it go with it, then its scenes are closed."""
        for run_id in [r for r, c in self._contexts.items() if c.scenes is old]:
            del self._contexts[run_id]
        old.close()

    def _victim(self, config: RunConfig, task: str) -> Any:
        from undream.victims import load_victim

        key = (config.victim, config.device, task)
        if key in self._victims:
            return self._victims.touch(key)
        victim = load_victim(config.victim, device=config.device, task=task, offline=self.local.hf_offline,
                             cache_home=self.local.cache_home)
        self.built["victims"] += 1
        return self._victims.put(key, victim)

    def __contains__(self, run_id: str) -> bool:
        return run_id in self._contexts

    def clear(self) -> None:
        self._contexts.clear()
        self._victims.clear()
        self._scenes.clear()  # each closed, least recently used first
