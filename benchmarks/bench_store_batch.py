#!/usr/bin/env python
"""Time recording one iteration's frame jobs in the store: one by one versus one batch.

    .venv/bin/python benchmarks/bench_store_batch.py [--frames 18] [--size 128] [--reps 20]

On SQLite in a temporary folder, records ``--frames`` frames with
``--size``×``--size``×3 float32 gradients either as ``job_started`` +
``job_succeeded`` per frame or as one ``jobs_started`` + one ``jobs_succeeded``,
and prints the median wall time of ``--reps`` repetitions of each (a fresh
iteration ``k`` per repetition). Run it alone: the machine's load shows in the numbers.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from undream.store import JobResult, Store, open_store


def _one_by_one(store: Store, run_id: str, k: int, results: list[JobResult]) -> None:
    for r in results:
        store.job_started(run_id, k, r.frame)
        store.job_succeeded(run_id, k, r.frame, r.grad, r.loss, r.finite, r.timings, r.result)


def _batch(store: Store, run_id: str, k: int, results: list[JobResult]) -> None:
    store.jobs_started(run_id, k, [r.frame for r in results])
    store.jobs_succeeded(run_id, k, results)


def median_seconds(record: Callable[[Store, str, int, list[JobResult]], None], frames: int, size: int,
                   reps: int, rng: np.random.Generator) -> float:
    """Median seconds of ``reps`` calls of ``record`` on a fresh SQLite store."""
    results = [JobResult(f, rng.normal(size=(size, size, 3)).astype(np.float32), 0.5, True,
                         {"render_s": 1.0}, {"label": "car"}) for f in range(frames)]
    with tempfile.TemporaryDirectory() as tmp, open_store(f"sqlite:///{Path(tmp) / 'runs.db'}",
                                                          Path(tmp) / "blobs") as store:
        run_id = store.create_run("bench", {}, n_frames=frames, seed=0)
        times = []
        for k in range(reps):
            start = time.perf_counter()
            record(store, run_id, k, results)
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=18)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--reps", type=int, default=20)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    single = median_seconds(_one_by_one, args.frames, args.size, args.reps, rng)
    batch = median_seconds(_batch, args.frames, args.size, args.reps, rng)
    print(f"{args.frames} frames, {args.size}×{args.size}×3 float32 gradients, SQLite, "
          f"median of {args.reps}:")
    print(f"  one by one (job_started + job_succeeded each): {single * 1e3:8.1f} ms")
    print(f"  batch (jobs_started + jobs_succeeded):         {batch * 1e3:8.1f} ms  ({batch / single:.2f}×)")


if __name__ == "__main__":
    main()
