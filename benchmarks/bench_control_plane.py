#!/usr/bin/env python
"""Time ``undream status`` over a farm database of many runs; print a table.

    .venv/bin/python benchmarks/bench_control_plane.py --runs 20000 [--repo DIR ...]

Seeds a SQLite farm database with ``--runs`` runs in mixed states (queued,
running with a frame job per frame, evaluating, done, failed; in 20 sweeps),
then runs ``undream status`` as a user would (a subprocess) with the code of
each ``--repo`` (default: this checkout; give a git worktree of an older
commit to compare), and prints its wall time and output size. Run it alone:
the machine's load shows in the numbers.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STATES = ("queued", "running", "evaluating", "done", "failed")


def seed(blobs: Path, n_runs: int, n_frames: int = 8) -> None:
    """``n_runs`` rows, bulk-inserted (minutes of one-by-one create_run calls otherwise)."""
    from sqlalchemy import insert

    from undream.spec.run import RunConfig
    from undream.store import open_store
    from undream.store.models import FrameJob, Run, Sweep, utcnow

    with open_store(None, blobs) as store:
        now = utcnow()
        sweeps = [{"id": str(uuid.uuid4()), "name": f"sweep{i}", "spec_json": "{}", "created": now} for i in range(20)]
        runs, jobs = [], []
        for i in range(n_runs):
            config = RunConfig.from_json({"scene": "s", "name": f"r{i}", "attack": {"name": "pgd", "steps": 10}})
            state = STATES[i % len(STATES)]
            run_id = str(uuid.uuid4())
            runs.append({"id": run_id, "name": config.name, "config_json": json.dumps(config.to_json()),
                         "status": state, "iteration": {"queued": 0, "running": 4}.get(state, 10),
                         "n_frames": n_frames, "seed": 0, "created": now, "updated": now,
                         "sweep_id": sweeps[i % 20]["id"], "farm_json": "{}", "failures": 0})
            if state == "running":
                jobs += [{"run_id": run_id, "phase": "attack", "k": 4, "frame": f,
                          "status": "succeeded" if f % 2 else "queued", "attempts": 0, "finite": True,
                          "timings_json": "{}"} for f in range(n_frames)]
        with store.engine.begin() as conn:
            conn.execute(insert(Sweep.__table__), sweeps)
            for i in range(0, len(runs), 5000):
                conn.execute(insert(Run.__table__), runs[i:i + 5000])
            for i in range(0, len(jobs), 20000):
                conn.execute(insert(FrameJob.__table__), jobs[i:i + 20000])


def time_status(repo: Path, blobs: Path) -> tuple[float, int, int]:
    """(seconds, output bytes, exit status) of ``undream status`` run with ``repo``'s code."""
    env = {**os.environ, "UNDREAM_BLOB_URL": str(blobs), "PYTHONPATH": str(repo)}
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "undream.cli", "status"], cwd=repo, env=env,
                         capture_output=True, text=True)
    return time.perf_counter() - t0, len(res.stdout.encode()), res.returncode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100_000, help="runs to seed (default 100000)")
    parser.add_argument("--repo", type=Path, action="append", default=None,
                        help="a checkout whose code runs `undream status` (repeatable; default this one)")
    args = parser.parse_args(argv)
    repos = args.repo or [ROOT]
    with tempfile.TemporaryDirectory(prefix="undream-bench-cp-") as tmp:
        blobs = Path(tmp) / "blobs"
        t0 = time.perf_counter()
        seed(blobs, args.runs)
        print(f"seeded {args.runs} runs in {time.perf_counter() - t0:.1f} s; load average "
              f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores\n")
        print("| code | runs | `undream status` s | × the first code's time | output bytes | exit |")
        print("|---|---|---|---|---|---|")
        first = None
        for repo in repos:
            seconds, size, rc = time_status(repo.resolve(), blobs)
            first = first or seconds
            print(f"| {repo} | {args.runs} | {seconds:.2f} | {seconds / first:.2f} | {size} | {rc} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
