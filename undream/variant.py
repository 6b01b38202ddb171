"""Choosing a Mitsuba variant, lazily: nothing happens at import time.

Mitsuba's JIT is not fork-safe, so only call :func:`mitsuba` in the process
that renders (a worker child, a CLI command, a test).

Without a variant asked for (``$UNDREAM_MI_VARIANT``, read at the edge by
:func:`undream.settings.load_local`) the first working variant of
:data:`PREFERRED` is used: ``cuda_ad_rgb`` on a machine (or container) that
has an NVIDIA GPU, its driver and OptiX, else ``llvm_ad_rgb`` on the CPU. A
fall-back from CUDA is logged (logger ``undream.variant``, level INFO: worker
logs show it) with the reason CUDA failed, found by :func:`cuda_unusable_reason`.
"""
from __future__ import annotations

import ctypes
import logging
from types import ModuleType
from typing import Callable

from undream.errors import RenderError

PREFERRED = ("cuda_ad_rgb", "llvm_ad_rgb")
# Mitsuba 3.9.1 deadlocks writing or reading an EXR (a run's texture, a scene's bitmaps) when Dr.Jit's
# pool has fewer than two threads: OpenEXR hands its work to tasks no thread runs, and the call waits
# forever. Dr.Jit's default pool is the cores the process may use, so on a one-core machine, container
# or cpuset (taskset -c 0) every render would hang; a pool of one asked for gets two (on one core).
MIN_DRJIT_POOL = 2
log = logging.getLogger(__name__)


def set_drjit_pool(threads: int | None = None) -> int:
    """Size Dr.Jit's thread pool: ``threads`` (None: Dr.Jit's default, the cores this process may
    use), never fewer than :data:`MIN_DRJIT_POOL`; returns the size it has."""
    import drjit as dr

    wanted = max(threads if threads is not None else dr.thread_count(), MIN_DRJIT_POOL)
    if dr.thread_count() != wanted:
        dr.set_thread_count(wanted)
    return wanted


def mitsuba(variant: str | None = None, *, libcuda: str = "libcuda.so.1",
            visible_devices: str | None = None) -> ModuleType:
    """Import Mitsuba with a differentiable RGB variant set and return the module.

    ``variant`` forces one (the edge passes ``$UNDREAM_MI_VARIANT`` here once,
    before anything renders); otherwise the first of ``cuda_ad_rgb``,
    ``llvm_ad_rgb`` that works is used. A variant already set is kept when
    none is asked for. RenderError naming every variant's reason when none
    works. ``libcuda`` and ``visible_devices``: see :func:`cuda_unusable_reason`.
    """
    import mitsuba as mi

    wanted = variant
    if wanted is None and mi.variant() is not None:
        return mi
    candidates = (wanted,) if wanted else PREFERRED
    failed: list[tuple[str, str]] = []  # (variant, why not)
    for name in candidates:
        if name not in mi.variants():
            failed.append((name, "not compiled in this mitsuba build"))
            continue
        try:
            mi.set_variant(name)
            if name.startswith("cuda"):
                import drjit as dr
                dr.zeros(mi.Float, 1)  # fails here when no GPU/driver is present
        except Exception as err:  # mitsuba raises plain ImportError/RuntimeError
            failed.append((name, cuda_unusable_reason(err, libcuda=libcuda, visible_devices=visible_devices)
                           if name.startswith("cuda") else _one_line(err)))
            continue
        if failed:
            log.info("falling back to Mitsuba variant %s: %s", name,
                     "; ".join(f"{n} failed: {why}" for n, why in failed))
        set_drjit_pool()  # its size as it is, but never below MIN_DRJIT_POOL, whoever renders next
        return mi
    raise RenderError("no usable Mitsuba variant (" + "; ".join(f"{n}: {why}" for n, why in failed) +
                      "); the CPU variant needs libLLVM >= 16 (Debian: apt-get install libllvm19)")


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split()) or type(err).__name__


def cuda_unusable_reason(err: BaseException, load: Callable[[str], ctypes.CDLL] = ctypes.CDLL, *,
                         libcuda: str = "libcuda.so.1", visible_devices: str | None = None) -> str:
    """Why Dr.Jit's CUDA backend failed, in words: no driver, no device, no OptiX, or Dr.Jit's ``err``.

    Dr.Jit only says that "the CUDA backend hasn't been initialized"; this asks
    the driver library itself (``libcuda``: ``$DRJIT_LIBCUDA_PATH`` or
    ``libcuda.so.1``, as Dr.Jit does, passed from the edge) and OptiX's
    (``libnvoptix.so.1``, which the NVIDIA container toolkit mounts only with
    the ``graphics`` driver capability). ``visible_devices``: the
    ``CUDA_VISIBLE_DEVICES`` in force, named when no device is visible.
    ``load`` opens a shared library (injectable for tests).
    """
    driver = libcuda
    try:
        cuda = load(driver)
    except OSError:
        return (f"no NVIDIA driver ({driver} cannot be loaded: no GPU here, or a container started "
                "without the NVIDIA runtime: docker --gpus, a nvidia.com/gpu resource on Kubernetes)")
    try:
        status = cuda.cuInit(0)
        count = ctypes.c_int(0)
        if status == 0:
            status = cuda.cuDeviceGetCount(ctypes.byref(count))
    except (AttributeError, OSError) as exc:
        return f"{driver} is not a usable CUDA driver ({_one_line(exc)})"
    if status != 0:
        return f"the NVIDIA driver failed to start (CUDA error {status}; {_one_line(err)})"
    if count.value == 0:
        visible = visible_devices
        return "no CUDA device visible" + (f" (CUDA_VISIBLE_DEVICES={visible!r})" if visible is not None else "")
    try:
        load("libnvoptix.so.1")
    except OSError:
        return ("OptiX (libnvoptix.so.1) is missing; in a container set "
                "NVIDIA_DRIVER_CAPABILITIES=compute,utility,graphics")
    return _one_line(err)

