#!/usr/bin/env python
"""Time the control plane over a farm database of many runs, in SQLite and PostgreSQL; print a table.

    .venv/bin/python benchmarks/bench_control_plane.py [--runs 100000] [--database sqlite postgresql]

Seeds each database with ``--runs`` runs in mixed states (queued, running with a frame job per frame
and iteration records, evaluating, done with results, failed; in 20 sweeps), then times what a user
or a browser asks for: ``undream status`` and ``undream results SWEEP`` as subprocesses (a user's
command, start-up included), and the dashboard's runs page, ``/api/runs`` (its first and a later
page), ``/api/sweeps`` and a sweep's page through a warm Flask app (a running dashboard: its first
request, which opens the store, is not timed). Each is timed ``--repeat`` times: the table gives the
first time, the median and the answer's size. Goal (issue 24): each ≤ 1 s and ≤ 1 MB at 100,000 runs. Run it
alone: the machine's load shows in the numbers (printed with them).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
STATES = ("queued", "running", "evaluating", "done", "failed")
N_SWEEPS = 20
PG_ADMIN_URL = os.environ.get("UNDREAM_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def _results(i: int) -> str:
    """A done run's headline results, as the evaluation writes them (without per-frame rows)."""
    value = (i % 7) / 7
    block = {"metric": "accuracy", "value": value}
    return json.dumps({"benign": {"metric": "accuracy", "value": 1.0}, "adversarial": block,
                       "held_out": {"benign": {"value": 1.0}, "adversarial": block},
                       "attack_success": {"aggregate": {"success_rate": 1 - value}},
                       "loss_per_iteration": [5.0 - k / 10 for k in range(10)]})


def seed(url: str, blobs: Path, n_runs: int, n_frames: int = 8) -> None:
    """``n_runs`` rows and their jobs, bulk-inserted (minutes of one-by-one create_run calls otherwise)."""
    import datetime as dt

    from sqlalchemy import insert

    from undream.spec.run import RunConfig
    from undream.store import open_store
    from undream.store.models import FrameJob, IterationRecord, Run, Sweep, utcnow

    with open_store(url, blobs) as store:
        now = utcnow()
        sweeps = [{"id": str(uuid.uuid4()), "name": f"sweep{i}", "created": now,
                   "spec_json": json.dumps({"name": f"sweep{i}", "grid": {"attack.eps": [4, 8, 16, 32]}})}
                  for i in range(N_SWEEPS)]
        runs, jobs, iters = [], [], []
        for i in range(n_runs):
            config = RunConfig.from_json({"scene": "s", "name": f"r{i}",
                                          "attack": {"name": "pgd", "steps": 10, "eps": 4 << (i % 4)}})
            state = STATES[i % len(STATES)]
            run_id = str(uuid.uuid4())
            created = now + dt.timedelta(microseconds=i)
            runs.append({"id": run_id, "name": config.name, "config_json": json.dumps(config.to_json()),
                         "status": state, "iteration": {"queued": 0, "running": 4}.get(state, 10),
                         "n_frames": n_frames, "seed": 0, "created": created, "updated": created,
                         "sweep_id": sweeps[i % N_SWEEPS]["id"], "farm_json": "{}", "failures": 0,
                         "results_json": _results(i) if state == "done" else None})
            if state == "running":
                jobs += [{"run_id": run_id, "phase": "attack", "k": 4, "frame": f,
                          "status": "succeeded" if f % 2 else "queued", "attempts": 0, "finite": True,
                          "timings_json": "{}"} for f in range(n_frames)]
                iters += [{"run_id": run_id, "k": k, "loss_mean": 5.0 - k / 10, "n_ok": n_frames, "n_bad": 0,
                           "dropped_json": "[]", "per_frame_json": "[]", "created": created} for k in range(4)]
        with store.engine.begin() as conn:
            conn.execute(insert(Sweep.__table__), sweeps)
            for table, rows in ((Run, runs), (FrameJob, jobs), (IterationRecord, iters)):
                for i in range(0, len(rows), 5000):
                    conn.execute(insert(table.__table__), rows[i:i + 5000])


def cli(env: dict[str, str], *args: str) -> Callable[[], tuple[int, int]]:
    """A callable that runs ``undream ARGS`` as a user does and gives (exit status, output bytes)."""
    def call() -> tuple[int, int]:
        res = subprocess.run([sys.executable, "-m", "undream.cli", *args], cwd=ROOT, env=env,
                             capture_output=True, text=True)
        if res.returncode != 0:
            print(res.stderr[-2000:], file=sys.stderr)
        return res.returncode, len(res.stdout.encode())
    return call


def http(client: Any, url: str) -> Callable[[], tuple[int, int]]:
    def call() -> tuple[int, int]:
        answer = client.get(url)
        return answer.status_code, len(answer.data)
    return call


def timed(call: Callable[[], tuple[int, int]], repeat: int) -> tuple[float, float, int, int]:
    """(seconds of the first call, median seconds of ``repeat`` calls, bytes, status)."""
    seconds, out = [], (0, 0)
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = call()
        seconds.append(time.perf_counter() - t0)
    return seconds[0], statistics.median(seconds), out[1], out[0]


def measure(name: str, url: str | None, blobs: Path, repeat: int) -> list[tuple[Any, ...]]:
    from undream.dashboard import create_app
    from undream.settings import load_settings
    from undream.store import open_store

    env = {**os.environ, "UNDREAM_BLOB_URL": str(blobs), "PYTHONPATH": str(ROOT)}
    if url:
        env["UNDREAM_DATABASE_URL"] = url
    settings = load_settings(env={k: v for k, v in env.items() if k.startswith("UNDREAM_")})
    client = create_app(settings).test_client()
    assert client.get("/api/health").status_code == 200  # the store opened; no list read yet
    with open_store(url, blobs) as store:
        after = store.runs_page(limit=50).next
        sweep_id = store.find_sweep("sweep3").id
    checks = [
        ("`undream status`", cli(env, "status")),
        ("`undream status --state running`", cli(env, "status", "--state", "running")),
        ("`undream results sweep3`", cli(env, "results", "sweep3")),
        ("`undream results sweep3 --csv` (every run)", cli(env, "results", "sweep3", "--csv")),
        ("runs page `/`", http(client, "/")),
        ("`/api/runs` (first page, 50 runs)", http(client, "/api/runs")),
        ("`/api/runs?cursor=…` (next page)", http(client, f"/api/runs?cursor={after}")),
        ("`/api/runs?status=done&limit=500`", http(client, "/api/runs?status=done&limit=500")),
        ("`/api/sweeps`", http(client, "/api/sweeps")),
        ("sweep page `/sweeps/<id>`", http(client, f"/sweeps/{sweep_id}")),
    ]
    return [(name, what, *timed(call, repeat)) for what, call in checks]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100_000, help="runs to seed (default 100000)")
    parser.add_argument("--database", nargs="+", choices=("sqlite", "postgresql"), default=["sqlite", "postgresql"])
    parser.add_argument("--repeat", type=int, default=3, help="timings per check; the median is shown")
    args = parser.parse_args(argv)
    rows = []
    for name in args.database:
        with tempfile.TemporaryDirectory(prefix="undream-bench-cp-") as tmp:
            blobs, url, drop = Path(tmp) / "blobs", None, None
            if name == "postgresql":
                sys.path.insert(0, str(ROOT / "tests"))
                from farm_support import postgres_database

                url, drop = postgres_database(PG_ADMIN_URL)
            try:
                t0 = time.perf_counter()
                seed(url, blobs, args.runs)
                print(f"{name}: seeded {args.runs} runs in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
                rows += measure(name, url, blobs, args.repeat)
            finally:
                if drop is not None:
                    drop()
    print(f"{args.runs} runs in {N_SWEEPS} sweeps; load average {os.getloadavg()[0]:.2f} on "
          f"{os.cpu_count()} cores (the dashboard's first request of a page reads it all; later ones "
          "reuse the rows of finished runs)\n")
    print(f"| database | read | first, s | median of {args.repeat}, s | bytes | status |")
    print("|---|---|---|---|---|---|")
    for name, what, first, median, size, status in rows:
        print(f"| {name} | {what} | {first:.3f} | {median:.3f} | {size:,} | {status} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
