#!/usr/bin/env python
"""Sweep throughput: a 4-run sweep on one one-core worker, then on two, measured in one run; print a table.

    .venv/bin/python benchmarks/bench_sweep.py [--run examples/runs/bin_orbit_pgd.yaml] [--steps 15]
                                               [--runs 4] [--workers 1 2]

The sweep is ``--runs`` seeds of ``--run`` (the default main job: the animated orbit, bundled
classifier, PGD) cut to ``--steps`` attack iterations. For each worker count it starts that many
``undream worker`` processes, each one process with one Dr.Jit thread and pinned to a core of its
own (``taskset``), on a fresh store and Redis database, submits the sweep with ``undream sweep``
(the scene is packed once, before the clock starts), and times from the first frame job's start
to the last run's finish, from the store. The ratio is the one-worker time over each time (goal,
issue 24: two workers ≥ 1.85× one). Run it alone: the load average is printed with the numbers.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _workers(env: dict[str, str], root: Path, n: int) -> list[subprocess.Popen]:
    procs = []
    pin = shutil.which("taskset") is not None and (os.cpu_count() or 1) >= n
    for i in range(n):
        cmd = [sys.executable, "-m", "undream.cli", "worker", "--concurrency", "1", "--threads", "1",
               "--loglevel", "WARNING"]
        log = open(root / f"worker{i}.log", "w")
        procs.append(subprocess.Popen((["taskset", "-c", str(i)] if pin else []) + cmd, cwd=ROOT, env=env,
                                      stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
    return procs


def sweep_wall(args: argparse.Namespace, n_workers: int, sweep: Path, tmp: Path) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT / "tests"))
    from farm_support import finished_runs, redis_client, stop_workers, wait_for
    from undream.settings import load_settings
    from undream.store import open_farm_store

    root = tmp / f"w{n_workers}"
    root.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1",
           "UNDREAM_BROKER_URL": f"redis://127.0.0.1:6379/{args.db}", "UNDREAM_BLOB_URL": str(root / "blobs"),
           "UNDREAM_CACHE_DIR": str(root / "cache"), "UNDREAM_FARM_SLOTS": "2"}
    redis_client(args.db).flushdb()
    procs = _workers(env, root, n_workers)
    try:
        res = subprocess.run([sys.executable, "-m", "undream.cli", "sweep", str(sweep)], cwd=ROOT, env=env,
                             capture_output=True, text=True)
        assert res.returncode == 0, res.stderr[-2000:]
        settings = load_settings(env={k: v for k, v in env.items() if k.startswith("UNDREAM_")})
        with open_farm_store(settings) as store:
            runs = wait_for(lambda: finished_runs(store, args.runs), args.timeout,
                            f"{n_workers} worker(s): the sweep to finish", interval=0.5)
            bad = [(r.name, r.status, r.error) for r in runs if r.status != "done"]
            assert not bad, bad
            starts = [j.started for r in runs for j in store.jobs(r.id, 0) if j.started]
            wall = (max(r.updated for r in runs) - min(starts)).total_seconds()
    finally:
        stop_workers(procs, 30)
    return {"workers": n_workers, "wall": wall}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, default=ROOT / "examples/runs/bin_orbit_pgd.yaml")
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--db", type=int, default=12, help="Redis database number to use (flushed)")
    parser.add_argument("--timeout", type=float, default=1800)
    args = parser.parse_args(argv)
    config = yaml.safe_load(args.run.read_text())
    config["attack"] = {**config.get("attack", {}), "steps": args.steps}
    config["scene"] = str((args.run.parent / config["scene"]).resolve())
    rows, load0 = [], os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="undream-bench-sweep-") as tmp:
        run = Path(tmp) / "run.yaml"
        run.write_text(yaml.safe_dump(config))
        sweep = Path(tmp) / "sweep.yaml"
        sweep.write_text(yaml.safe_dump({"name": "bench-sweep", "run": str(run),
                                         "grid": {"seed": list(range(args.runs))}}))
        for n in args.workers:
            rows.append(sweep_wall(args, n, sweep, Path(tmp)))
            print(f"{n} worker(s): {rows[-1]['wall']:.1f} s", file=sys.stderr)
    print(f"{args.runs}-run sweep of {args.run.name} at {args.steps} iterations; one-core workers (one process, "
          f"one Dr.Jit thread, pinned); load average {load0:.2f} before, {os.getloadavg()[0]:.2f} after, "
          f"on {os.cpu_count()} cores\n")
    print("| workers | sweep wall, s | × one worker |")
    print("|---|---|---|")
    for r in rows:
        print(f"| {r['workers']} | {r['wall']:.1f} | {rows[0]['wall'] / r['wall']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
