"""Benchmark the farm against one process, measured in one run:

    python benchmarks/farm.py [--scene examples/bin_park.yaml] [--steps 12]

The same run (the default example, bundled classifier, PGD) goes through

1. one process (``undream run``'s path, Dr.Jit's default pool);
2. Redis and one ``undream worker`` with the machine's cores (Dr.Jit default);
3. Redis and one worker pinned to one core ("one Dr.Jit thread": a pool of two
   on one core, see workers/runtime.py for why not a pool of one);
4. Redis and two workers pinned to one core each;

with the texture gradient from the captured transport (``gradient: auto``, the
default: a per-process cache, captured again by a worker that gets a frame it
has not served) and from Mitsuba's prb pass (``gradient: prb``, no cache). The
tables give, for each: the wall time of the attack iterations after
the first (kernels compiled, contexts built), frames per second there, the
ratio to one process (time) or to the one-core worker (throughput); the
scheduling gap (from an iteration's last frame job finishing to the next
iteration's first frame job starting, median and max); and bytes moved per
frame job (blob reads and writes, broker traffic). Uses the Redis at
``--redis`` (database 14, flushed) and prints the machine's load.
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


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="examples/bin_park.yaml", help="scene directory or spec file")
    p.add_argument("--victim", default="bundled:classifier")
    p.add_argument("--steps", type=int, default=12)
    p.add_argument("--sim-spp", type=int, default=16)
    p.add_argument("--grad-spp", type=int, default=8)
    p.add_argument("--eval-spp", type=int, default=8)
    p.add_argument("--redis", default="127.0.0.1:6379")
    p.add_argument("--db", type=int, default=14, help="Redis database number to use (flushed)")
    p.add_argument("--gradient", nargs="+", default=["auto", "prb"], help="gradient paths to measure")
    return p.parse_args(argv)


def _steady(store: Any, run_id: str, steps: int, n_frames: int) -> dict[str, float]:
    """Iterations 1 … steps−1 from the job rows: wall time, frames/s, scheduling gaps."""
    by_k = {k: store.jobs(run_id, k) for k in range(steps)}
    start = min(j.started for j in by_k[1])
    end = max(j.finished for j in by_k[steps - 1])
    wall = (end - start).total_seconds()
    gaps = [(min(j.started for j in by_k[k + 1]) - max(j.finished for j in by_k[k])).total_seconds()
            for k in range(1, steps - 1)]
    jobs = [j for k in range(1, steps) for j in by_k[k]]
    # per frame job, summed over the steady jobs and divided by their count: where a frame's time goes
    parts = {part: sum(j.timings.get(part, 0.0) for j in jobs) / len(jobs)
             for part in ("sim_render", "victim", "grad_render")}
    # a task's own wall per frame (its frames' first start to last finish, by worker and iteration):
    # what the parts leave out is the task's store writes and reads
    tasks: dict[tuple[Any, int], list[Any]] = {}
    for j in jobs:
        tasks.setdefault((j.worker, j.k), []).append(j)
    task_wall = sum((max(j.finished for j in t) - min(j.started for j in t)).total_seconds()
                    for t in tasks.values()) / len(jobs)
    return {"wall": wall, "fps": (steps - 1) * n_frames / wall, "gap_median": statistics.median(gaps),
            "gap_max": max(gaps), "task_wall": task_wall, **parts}


def _blob_bytes(store: Any, run_id: str, fpt: int) -> float:
    """Blob bytes per frame job: its gradient written, the texture read once per task.

    A frame's gradient is an H×W×3 float32 array like the texture (and is deleted once its
    iteration is reduced, so the texture's size stands for it)."""
    tex = store.blobs.size(f"runs/{run_id}/texture/000001.npy")
    return tex + tex / fpt


class Farm:
    def __init__(self, root: Path, args: argparse.Namespace, **settings: Any) -> None:
        self.root, self.args = root, args
        self.env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HUB_DISABLE_PROGRESS_BARS": "1",
                    "UNDREAM_BROKER_URL": f"redis://{args.redis}/{args.db}",
                    "UNDREAM_BLOB_URL": str(root / "blobs"), "UNDREAM_CACHE_DIR": str(root / "cache"),
                    **{f"UNDREAM_{k.upper()}": str(v) for k, v in settings.items()}}
        self.procs: list[subprocess.Popen] = []

    def start(self, n: int, threads: int | None) -> None:
        for i in range(n):
            log = open(self.root / f"worker{i}.log", "w")
            cmd = [sys.executable, "-m", "undream.cli", "worker", "--loglevel", "WARNING"]
            if threads:
                cmd += ["--threads", str(threads)]
            self.procs.append(subprocess.Popen(cmd, cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                               start_new_session=True))
        time.sleep(4)  # the workers connect

    def stop(self) -> None:
        for p in self.procs:
            os.killpg(p.pid, 15)
            p.wait(30)


def _farm_run(root: Path, args: argparse.Namespace, prepared: Any, workers: int, threads: int | None,
              redis: Any) -> dict[str, Any]:
    from scheduler.submit import record
    from undream.settings import load_settings
    from undream.store import open_farm_store
    from workers.app import create_celery_app
    from workers.dispatch import CeleryDispatch

    root.mkdir(parents=True)
    farm = Farm(root, args, farm_slots=workers)
    settings = load_settings(env=farm.env)
    redis.flushdb()
    farm.start(workers, threads)
    try:
        store = open_farm_store(settings)
        app = create_celery_app(settings)
        (run_id,) = record(store, [prepared], settings)
        net0 = redis.info("stats")
        t0 = time.perf_counter()
        CeleryDispatch(app).start(run_id)
        while store.get_run(run_id).status not in ("done", "failed"):
            time.sleep(0.05)
        total = time.perf_counter() - t0
        net1 = redis.info("stats")
        run = store.get_run(run_id)
        if run.status != "done":
            raise SystemExit(f"farm run failed: {run.error}")
        n_jobs = sum(len(store.jobs(run_id, None, p)) for p in ("attack", "pre", "adversarial"))
        broker = sum(net1[k] - net0[k] for k in ("total_net_input_bytes", "total_net_output_bytes"))
        fpt = run.farm["frames_per_task"]
        return {**_steady(store, run_id, args.steps, prepared.n_frames), "total": total,
                "blob_bytes": _blob_bytes(store, run_id, fpt), "broker_bytes": broker / n_jobs, "fpt": fpt}
    finally:
        farm.stop()


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    os.chdir(ROOT)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ["HF_HUB_DISABLE_PROGRESS_BARS"] = "1"
    import redis as redis_py

    from scheduler.submit import Validator
    from undream.spec.run import RunConfig

    host, port = args.redis.split(":")
    redis = redis_py.Redis(host=host, port=int(port), db=args.db)
    tmp = Path(tempfile.mkdtemp(prefix="undream-farm-bench-"))
    print(f"uptime before: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    validate = Validator(tmp / "work")
    for gradient in args.gradient:
        config = RunConfig(scene=str(Path(args.scene).resolve()), name="bench", victim=args.victim,
                           attack={"name": "pgd", "eps": 16, "steps": args.steps}, sim_spp=args.sim_spp,
                           grad_spp=args.grad_spp, eval_spp=args.eval_spp, gradient=gradient)
        _table(args, validate(config, ROOT), tmp / gradient, redis)
    print(f"uptime after: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")


def _table(args: argparse.Namespace, prepared: Any, tmp: Path, redis: Any) -> None:
    import yaml

    from undream.store import open_store

    load0 = os.getloadavg()
    tmp.mkdir(parents=True)
    run_yaml = tmp / "run.yaml"  # the local run in a fresh process, like the workers
    run_yaml.write_text(yaml.safe_dump({**prepared.config.to_json(), "scene": str(prepared.scene_dir)},
                                       sort_keys=False))  # a grid's key order orders its conditions
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "undream.cli", "run", str(run_yaml), "--out", str(tmp / "local"),
                    "--no-progress"], check=True, cwd=ROOT, capture_output=True)
    local_total = time.perf_counter() - t0
    store = open_store(None, tmp / "local" / "store")
    run_id = store.runs()[0].id
    local = {**_steady(store, run_id, args.steps, prepared.n_frames), "total": local_total,
             "blob_bytes": _blob_bytes(store, run_id, prepared.n_frames), "broker_bytes": 0.0,
             "fpt": prepared.n_frames}

    rows = [("one process (undream run)", local)]
    for label, workers, threads in (("Redis, 1 worker, all cores", 1, None),
                                    ("Redis, 1 worker, 1 core", 1, 1),
                                    ("Redis, 2 workers, 1 core each", 2, 1)):
        rows.append((label, _farm_run(tmp / label.split(",")[1].strip().replace(" ", "_") /
                                      (label.split(",")[-1].strip().replace(" ", "_")), args, prepared,
                                      workers, threads, redis)))
    load1 = os.getloadavg()

    one_core = rows[2][1]["fps"]
    print(f"\nfarm benchmark: {args.scene}, {prepared.n_frames} frames, {args.steps} PGD steps, "
          f"gradient {prepared.config.gradient}, "
          f"sim_spp {args.sim_spp}, grad_spp {args.grad_spp}, eval_spp {args.eval_spp}; "
          f"{os.cpu_count()} cores; load average before {load0[0]:.2f}, after {load1[0]:.2f}")
    print("steady = iterations 1…N−1 (after compilation and context builds); per frame: the steady jobs' own "
          "timings, and each task's wall (first start to last finish) per frame\n")
    head = ("setup", "frames/task", "steady s", "frames/s", "time vs 1 process", "throughput vs 1-core worker",
            "gap median ms", "gap max ms", "blob B/job", "broker B/job", "total s",
            "per frame: sim ms", "victim ms", "grad ms", "task wall ms")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for label, r in rows:
        print(f"| {label} | {r['fpt']} | {r['wall']:.2f} | {r['fps']:.1f} | {r['wall'] / local['wall']:.2f} | "
              f"{r['fps'] / one_core:.2f} | {1000 * r['gap_median']:.1f} | {1000 * r['gap_max']:.1f} | "
              f"{r['blob_bytes']:.0f} | {r['broker_bytes']:.0f} | {r['total']:.1f} | "
              f"{1000 * r['sim_render']:.1f} | {1000 * r['victim']:.1f} | {1000 * r['grad_render']:.1f} | "
              f"{1000 * r['task_wall']:.1f} |")


if __name__ == "__main__":
    main()
