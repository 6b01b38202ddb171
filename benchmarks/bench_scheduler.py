#!/usr/bin/env python
"""Scheduler throughput: frame jobs per second the broker and the database sustain, and the gap
between iterations, with K workers on runs whose frame jobs do almost nothing; print a table.

    .venv/bin/python benchmarks/bench_scheduler.py [--workers 8] [--runs 4] [--frames 32] [--steps 12]
                                                   [--database sqlite postgresql]

Each run attacks a 16 px scene of ``--frames`` frames with a tiny victim, one frame per task
(``frames_per_task: 1``: the most scheduling per frame). In the workers (real ``undream worker``
processes, one slot each, over the real Redis) the attack job's render, victim and gradient are
replaced by a zero gradient: a job still records its start, writes its gradient blob and records
its result, and each iteration is still a Celery chord whose callback reduces, steps and sends the
next one. So what is timed is the farm's own work. From the job rows of iterations 1 … steps−2
(workers warm): **jobs/s** (attack jobs finished in that window over its length, all runs
together), the **gap** (an iteration's last job finished → the next iteration's first job
started, per run and iteration: chord completion, the callback's reduce and step, the next chord's
delivery), the time a job spends from its start to its result, and the Redis commands per job
(every job of every phase: all the server processed while the runs ran, the workers' polling
included). Run it alone: the machine's load is printed with the numbers.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PG_ADMIN_URL = os.environ.get("UNDREAM_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def null_frame_jobs(store: Any, ctx: Any, run_id: str, k: int, positions: list[int],
                    texture: Any = None) -> list[dict[str, Any]]:
    """:func:`scheduler.iteration.frame_jobs` with the engine left out: a zero gradient per frame."""
    import numpy as np

    from scheduler.iteration import worker_name
    from undream.store import JobResult

    store.jobs_started(run_id, k, positions, worker=worker_name())
    zero = np.zeros_like(store.texture(run_id, k) if texture is None else texture, dtype=np.float32)
    store.jobs_succeeded(run_id, k, [JobResult(frame=f, grad=zero, loss=1.0, finite=True, timings={"total": 0.0},
                                               result={}) for f in positions])
    return [{"frame": f, "loss": 1.0, "finite": True} for f in positions]


def worker_main() -> None:
    """An ``undream worker`` (settings from the environment) whose attack jobs are null jobs."""
    import scheduler.stages
    from undream.settings import load_settings
    from workers.main import run_worker

    scheduler.stages.frame_jobs = null_frame_jobs  # inherited by the forked worker process
    run_worker(load_settings(env=dict(os.environ)), "WARNING")


def _env(root: Path, db: int, url: str | None) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1",
           "UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{db}", "UNDREAM_BLOB_URL": str(root / "blobs"),
           "UNDREAM_CACHE_DIR": str(root / "cache"), "UNDREAM_FRAMES_PER_TASK": "1",
           "UNDREAM_CONCURRENCY": "1", "UNDREAM_DRJIT_THREADS": "1"}
    if url:
        env["UNDREAM_DATABASE_URL"] = url
    return env


def _steady(store: Any, run_id: str, steps: int) -> tuple[list[Any], list[float]]:
    """The attack jobs of iterations 1 … steps−2 and the gaps between them."""
    by_k = {k: store.jobs(run_id, k) for k in range(1, steps - 1)}
    gaps = [(min(j.started for j in by_k[k + 1]) - max(j.finished for j in by_k[k])).total_seconds()
            for k in range(1, steps - 2)]
    return [j for jobs in by_k.values() for j in jobs], gaps


def measure(name: str, args: argparse.Namespace, inputs: dict[str, Any]) -> dict[str, Any]:
    import yaml

    from farm_support import finished_runs, postgres_database, redis_client, run_config, stop_workers, wait_for
    from undream.store import open_store

    url, drop = postgres_database(PG_ADMIN_URL) if name == "postgresql" else (None, None)
    redis_client(args.db).flushdb()
    with tempfile.TemporaryDirectory(prefix="undream-bench-sched-") as tmp:
        root = Path(tmp)
        env = _env(root, args.db, url)
        workers = []
        try:
            for i in range(args.workers):
                log = open(root / f"worker{i}.log", "w")
                workers.append(subprocess.Popen([sys.executable, __file__, "--worker"], cwd=ROOT, env=env,
                                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
            run = run_config(inputs["scene"], inputs["victim"], name="null", steps=args.steps)
            sweep = {"name": "sched", "run": str(root / "run.yaml"), "grid": {"seed": list(range(args.runs))}}
            (root / "run.yaml").write_text(yaml.safe_dump(run))
            (root / "sweep.yaml").write_text(yaml.safe_dump(sweep))
            commands0 = redis_client(args.db).info("stats")["total_commands_processed"]
            t0 = time.monotonic()
            res = subprocess.run([sys.executable, "-m", "undream.cli", "sweep", str(root / "sweep.yaml")],
                                 cwd=ROOT, env=env, capture_output=True, text=True)
            assert res.returncode == 0, res.stderr
            with open_store(url, root / "blobs") as store:
                runs = wait_for(lambda: finished_runs(store, args.runs), args.timeout - (time.monotonic() - t0),
                                f"{name}: the runs to finish", interval=0.5)
                commands = redis_client(args.db).info("stats")["total_commands_processed"] - commands0
                n_jobs = sum(len(store.jobs(r.id, None, phase)) for r in runs for phase in ("attack", "pre", "adversarial"))
                bad = [r for r in runs if r.status != "done"]
                assert not bad, [(r.status, r.error) for r in bad]
                jobs, gaps = [], []
                for r in runs:
                    j, g = _steady(store, r.id, args.steps)
                    jobs += j
                    gaps += g
        finally:
            stop_workers(workers, 20)
            if drop is not None:
                drop()
    start, end = min(j.started for j in jobs), max(j.finished for j in jobs)
    held = sorted((j.finished - j.started).total_seconds() for j in jobs)
    gaps.sort()
    return {"database": name, "jobs": len(jobs), "jobs_per_s": len(jobs) / (end - start).total_seconds(),
            "gap_median_ms": 1000 * statistics.median(gaps), "gap_p90_ms": 1000 * gaps[int(0.9 * (len(gaps) - 1))],
            "job_median_ms": 1000 * statistics.median(held), "job_p90_ms": 1000 * held[int(0.9 * (len(held) - 1))],
            "redis_per_job": commands / n_jobs}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--workers", type=int, default=8, help="worker processes, one slot each (default 8)")
    parser.add_argument("--runs", type=int, default=4, help="runs at once (default 4)")
    parser.add_argument("--frames", type=int, default=32, help="frames per run, one job each (default 32)")
    parser.add_argument("--steps", type=int, default=12, help="attack iterations per run (default 12)")
    parser.add_argument("--database", nargs="+", choices=("sqlite", "postgresql"), default=["sqlite", "postgresql"])
    parser.add_argument("--db", type=int, default=13, help="Redis database number to use (flushed)")
    parser.add_argument("--timeout", type=float, default=900)
    args = parser.parse_args(argv)
    if args.worker:
        worker_main()
        return 0
    sys.path.insert(0, str(ROOT / "tests"))
    from farm_support import make_scene, make_victim

    with tempfile.TemporaryDirectory(prefix="undream-bench-sched-in-") as tmp:
        inputs = {"scene": make_scene(Path(tmp) / "scene", n_frames=args.frames, size=16),
                  "victim": make_victim(Path(tmp) / "victim")}
        load0 = os.getloadavg()[0]
        rows = [measure(name, args, inputs) for name in args.database]
    print(f"{args.workers} workers (one slot each), {args.runs} runs × {args.frames} frames × {args.steps} "
          f"iterations, one frame per task, null jobs; iterations 1 … {args.steps - 2} of each run; load "
          f"average {load0:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} cores\n")
    print("| database | jobs | jobs/s | gap median, ms | gap p90, ms | job start → result median, ms | p90, ms "
          "| Redis commands per job |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['database']} | {r['jobs']} | {r['jobs_per_s']:.0f} | {r['gap_median_ms']:.1f} | "
              f"{r['gap_p90_ms']:.1f} | {r['job_median_ms']:.1f} | {r['job_p90_ms']:.1f} | {r['redis_per_job']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
