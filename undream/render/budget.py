"""Memory and time a sequence's renders need, estimated before anything renders.

A render's memory grows with its pixels, not with its samples: Mitsuba's
integrators run their sample loops inside one kernel, so what stays is the
film and the image. Measured here (``llvm_ad_rgb``, the default example's
simulation and gradient scenes, peak RSS of a fresh process before and after
one render): 34 bytes per pixel at 2048² (1, 4 and 16 spp alike) and 30 at
4096² (1 and 4 spp); 32–131 at 256–1024 px, where a fixed ~10–30 MB of
kernels and buffers dominates (up to 256 spp). Around each
frame undream holds a few H×W×3 float32 copies (linear, sRGB, its gradient,
the 8-bit frame), about 60 bytes per pixel more. A frame's captured transport
holds about 10 bytes per gradient sample (3.95 / 11.7 / 20.9 MB per frame at
64 / 256 / 512 px and 8 spp), up to ``MAX_TRANSPORT_BYTES`` in all.

Time: the same renders ran at 1.5–6.3 million samples per second on this
machine's two cores; :data:`CPU_SAMPLES_PER_SECOND` is a rough middle, good
for an order of magnitude, not a promise (a GPU is far faster).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Iterable

from undream.errors import SpecError
from undream.settings import MEMORY_LIMIT_ENV
from undream.spec import Sequence
from undream.spec.run import RunConfig

RENDER_BYTES_PER_PIXEL = 40  # Mitsuba's film and image (measured 30–34 at 2048² and up)
HOST_BYTES_PER_PIXEL = 60  # undream's float32 copies of a frame
FIXED_BYTES = 64 << 20  # kernels and buffers of any render (measured 10–30 MB)
TRANSPORT_BYTES_PER_SAMPLE = 10  # a captured transport, per gradient sample
MAX_TRANSPORT_BYTES = 4 << 30  # undream.engine.gradient's cap on captured transports
MAX_SAMPLES_PER_RENDER = 2**32 - 1  # Dr.Jit's wavefront: one lane per sample
CPU_SAMPLES_PER_SECOND = 3.0e6  # llvm_ad_rgb on 2 cores, measured 1.5–6.3 M/s


@dataclass(frozen=True)
class RenderJob:
    """One kind of render a run does: ``spp`` samples per pixel of a ``width``×``height`` frame."""

    field: str  # the config or spec field that sets it, for messages
    width: int
    height: int
    spp: int

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def samples(self) -> int:
        return self.pixels * self.spp

    @property
    def peak_bytes(self) -> int:
        return FIXED_BYTES + self.pixels * (RENDER_BYTES_PER_PIXEL + HOST_BYTES_PER_PIXEL)


@dataclass(frozen=True)
class Estimate:
    """What a run (or an init) needs: peak bytes in one process; samples and CPU seconds per ``unit``."""

    peak_bytes: int
    samples: int
    unit: str = "per iteration"

    @property
    def cpu_seconds(self) -> float:
        return self.samples / CPU_SAMPLES_PER_SECOND

    def describe(self) -> str:
        return (f"about {_size(self.peak_bytes)} of memory at peak; {self.samples / 1e6:.3g} M samples "
                f"{self.unit} (roughly {self.cpu_seconds:.2g} s on 2 CPU cores)")


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000:
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} TB"


def available_memory() -> int:
    """Bytes a render may use: the system's MemAvailable (a limit the user sets,
    ``$UNDREAM_MEMORY_LIMIT``, is read at the edge and passed as ``limit``)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_renders(jobs: Iterable[RenderJob], transport_samples: int = 0, limit: int | None = None) -> int:
    """Refuse renders that cannot run here; the peak bytes of those that can.

    SpecError naming the field when one render has more samples than Dr.Jit
    can index (2³² − 1), or when the largest render (plus the captured
    transports of ``transport_samples`` gradient samples) needs more memory
    than ``limit`` (bytes; None: :func:`available_memory`).
    """
    jobs = list(jobs)
    for job in jobs:
        if job.samples > MAX_SAMPLES_PER_RENDER:
            raise SpecError(f"{job.field}: {job.width}×{job.height} px at {job.spp} spp is {job.samples:,} "
                            f"samples in one render, more than Mitsuba can index ({MAX_SAMPLES_PER_RENDER:,}); "
                            "lower the resolution or the spp")
    transport = min(transport_samples * TRANSPORT_BYTES_PER_SAMPLE, MAX_TRANSPORT_BYTES)
    biggest = max(jobs, key=lambda j: j.peak_bytes)
    peak = biggest.peak_bytes + transport
    limit = available_memory() if limit is None else limit
    if peak > limit:
        raise SpecError(f"{biggest.field}: {biggest.width}×{biggest.height} px at {biggest.spp} spp needs about "
                        f"{_size(peak)} of memory and {_size(limit)} is available; lower the resolution "
                        f"(or set {MEMORY_LIMIT_ENV} if more is free)")
    return peak


def _frame_jobs(seq: Sequence, spp: int, what: str) -> list[RenderJob]:
    return [RenderJob(f"frames[{i}].camera.resolution with {what} {spp}", *f.camera.resolution, spp)
            for i, f in enumerate(seq.frames)]


def init_estimate(seq: Sequence, verify_spp: int, limit: int | None = None) -> Estimate:
    """Check and estimate ``undream init``'s verification renders (one per frame at ``verify_spp``)."""
    jobs = _frame_jobs(seq, verify_spp, "verify_spp")
    return Estimate(check_renders(jobs, limit=limit), sum(j.samples for j in jobs), "to verify")


def run_estimate(seq: Sequence, config: RunConfig, limit: int | None = None) -> Estimate:
    """Check and estimate a run: its simulator, gradient and evaluation renders, its transports."""
    per_step = config.attack.frames_per_step
    n = per_step if per_step is not None and per_step < len(seq.frames) else len(seq.frames)
    sim, grad = _frame_jobs(seq, config.sim_spp, "sim_spp"), _frame_jobs(seq, config.grad_spp, "grad_spp")
    evaluation = _frame_jobs(seq, config.eval_spp, "eval_spp")
    transport = 0 if config.gradient == "prb" else sum(j.samples for j in grad)
    peak = check_renders(sim + grad + evaluation, transport, limit)
    mean = sum(j.samples for j in sim + grad) / len(seq.frames)
    return Estimate(peak, round(mean * n))
