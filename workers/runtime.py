"""What a worker process holds: its store connection, its runs' contexts, its dispatch.

Built lazily in the process that runs tasks (a prefork child), never in the
worker's parent: database engines and Mitsuba's JIT are not fork-safe.
:func:`init_process` runs in each child as it starts (``worker_process_init``)
and sets the thread counts there. The process's :class:`~undream.settings.LocalSettings`
(``UNDREAM_MI_VARIANT``, ``UNDREAM_BLENDER_THREADS``, ...) are read once at
the worker's start (:func:`workers.app.create_celery_app`) and passed down;
nothing here writes the environment.
"""
from __future__ import annotations

from dataclasses import replace
import fcntl
import logging
import os
import time
from pathlib import Path
from typing import IO, TYPE_CHECKING

from scheduler.contexts import ContextCache
from undream.lru import LRU
from undream.settings import load_local
from undream.variant import mitsuba, set_drjit_pool
from workers.dispatch import CeleryDispatch

if TYPE_CHECKING:
    from celery import Celery

    from scheduler.contexts import ContextCache
    from undream.settings import LocalSettings, Settings
    from undream.store import Store
    from workers.dispatch import CeleryDispatch

log = logging.getLogger(__name__)

_HELD: list[IO[str]] = []  # lock files of the cores this process claimed (released when it exits)


class Runtime:
    """One process's store, context cache (LRU by run id) and Celery dispatch."""

    def __init__(self, app: "Celery") -> None:
        from scheduler.stages import TEXTURE_VERSIONS
        from undream.store import open_farm_store

        settings: Settings = app.undream_settings  # type: ignore[attr-defined]
        local: LocalSettings = app.undream_local  # type: ignore[attr-defined]
        self.pid = os.getpid()
        self.store: Store = open_farm_store(settings)
        self.contexts: ContextCache = ContextCache(self.store, settings.cache_dir, scenes=settings.scene_cache,
                                                   local=local, transport_cache_mb=settings.transport_cache_mb)
        self.dispatch: CeleryDispatch = CeleryDispatch(app)
        self.textures: LRU[tuple, dict] = LRU(TEXTURE_VERSIONS)  # texture versions read (run, phase, k)


def runtime(app: "Celery") -> Runtime:
    """This process's runtime for ``app`` (made on first use; a forked child makes its own)."""
    rt: Runtime | None = getattr(app, "_undream_runtime", None)
    if rt is None or rt.pid != os.getpid():
        rt = Runtime(app)
        app._undream_runtime = rt  # type: ignore[attr-defined]
    return rt


def drjit_threads_for(settings: "Settings") -> int:
    """Dr.Jit threads per worker process: as set, else the machine's cores shared among the processes."""
    return settings.drjit_threads or max(1, (os.cpu_count() or 1) // settings.concurrency)


def claim_cores(n: int, lock_dir: Path) -> list[int]:
    """Pin this process to ``n`` cores that no other worker process on the machine has claimed.

    Claims are ``flock`` s on ``lock_dir/coreN.lock``, released when the process
    exits (however it dies). Returns the cores; all of them (no pinning) when
    ``n`` covers the machine or not enough are free.
    """
    cores = sorted(os.sched_getaffinity(0))
    if n >= len(cores):
        return cores
    lock_dir.mkdir(parents=True, exist_ok=True)
    got: list[tuple[int, IO[str]]] = []
    for core in cores:
        f = open(lock_dir / f"core{core}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        got.append((core, f))
        if len(got) == n:
            break
    if len(got) < n:
        for _, f in got:
            f.close()
        log.warning("no %d free core(s) to pin this worker process to; it runs on all %d", n, len(cores))
        return cores
    _HELD.extend(f for _, f in got)
    pin_threads([c for c, _ in got])
    return [c for c, _ in got]


def pin_threads(cores: list[int]) -> None:
    """Pin every thread of this process to ``cores``: those started before (imports start some)
    as well as this one and those it starts later. ``sched_setaffinity(0, ...)`` alone pins the
    calling thread only: the earlier ones went on running on every core, so a "one-core" worker
    used the second core too, and two of them on two cores ran on each other's."""
    os.sched_setaffinity(0, cores)
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cores)
        except OSError:  # a thread that ended meanwhile
            pass


def init_process(settings: "Settings", local: "LocalSettings | None" = None) -> "LocalSettings":
    """In a worker child as it starts: its cores, Dr.Jit's, Cycles' and torch's thread counts, Mitsuba's variant.

    ``local``: the process's settings read at the worker's start (None: read
    here, :func:`undream.settings.load_local`). Returns them with Cycles'
    threads (``sim: blender``) set to the same share of cores as Dr.Jit unless
    ``$UNDREAM_BLENDER_THREADS`` said otherwise (its render server inherits
    the pinning too); the caller hands them to the process's :class:`Runtime`.
    """
    import drjit as dr
    import torch

    local = load_local() if local is None else local
    threads = drjit_threads_for(settings)
    cores = claim_cores(threads, Path(settings.cache_dir) / "cores")
    set_drjit_pool(threads)  # a worker that should use one core gets a pool of two pinned to it
    if local.blender_threads is None:
        local = replace(local, blender_threads=threads)
    torch.set_num_threads(settings.torch_threads)
    mitsuba(local.mi_variant, libcuda=local.libcuda_path, visible_devices=local.cuda_visible_devices)
    warm_up()
    log.info("worker process %d: cores %s, Dr.Jit pool %d, torch threads %d", os.getpid(), cores,
             dr.thread_count(), settings.torch_threads)
    return local


def warm_up() -> float:
    """Load the bundled classifier once and drop it: the victims' model code is imported while the
    worker waits for work, not in its first task (a worker's first victim took 2.4 s to load, the
    next 0.06 s). Returns the seconds it took; a failure is logged, never fatal."""
    from undream.victims import load_victim

    t0 = time.perf_counter()
    try:
        load_victim("bundled:classifier", device="cpu", task="classification", offline=True)
    except Exception as exc:  # the worker still serves runs: their victims load as before
        log.warning("worker process %d: warm-up skipped: %s", os.getpid(), exc)
    return time.perf_counter() - t0
