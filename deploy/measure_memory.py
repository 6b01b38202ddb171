#!/usr/bin/env python3
"""Peak memory of one farm worker process per resolution and frame count (the README's sizing table).

For each (px, frames) it starts a fresh ``undream worker --concurrency 1``
(SQLite and blobs in a temporary folder, the broker given), submits the
default example's run (the trash bin in the park, bundled classifier, PGD)
on an orbit of ``frames`` frames at ``px``×``px``, waits for it to finish and
reads the worker's processes from /proc: the child's peak resident set
(``VmHWM``: Mitsuba, Dr.Jit, torch, the victim, loaded scenes, captured
transports) and the parent's (Celery only). With ``--local`` it also runs the
same config with ``undream run`` (one process) and reports its peak (getrusage).

    .venv/bin/python deploy/measure_memory.py --px 64 256 --frames 8 32 --broker redis://127.0.0.1:6379/1
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _status_kib(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/{pid}/status has no {field}")


def _children(pid: int) -> list[int]:
    kids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(entry.name))
    return kids


def write_inputs(folder: Path, px: int, frames: int, steps: int) -> Path:
    """The default example on an orbit of ``frames`` frames at ``px`` px, and its run config."""
    spec = yaml.safe_load((ROOT / "examples" / "bin_park.yaml").read_text())
    spec["frames"] = frames
    spec["camera"]["resolution"] = [px, px]
    spec["camera"]["path"] = {"type": "orbit", "center": [0, 0, 0], "radius": 3.3, "height": 1.3,
                              "start_deg": 0, "end_deg": 90}
    (folder / "scene.yaml").write_text(yaml.safe_dump(spec))
    run = {"name": f"mem-{px}px-{frames}f", "scene": "scene.yaml", "victim": "bundled:classifier", "loss": "ce",
           "attack": {"name": "pgd", "eps": 16, "steps": steps}, "sim_spp": 16, "grad_spp": 8, "eval_spp": 16,
           "seed": 0}
    path = folder / "run.yaml"
    path.write_text(yaml.safe_dump(run))
    return path


def measure_worker(run_yaml: Path, folder: Path, broker: str, threads: int, timeout: float) -> dict[str, float]:
    """Peak RSS (MiB) of the worker's child and parent while running ``run_yaml``, and the wall time."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "UNDREAM_BROKER_URL": broker,
           "UNDREAM_BLOB_URL": str(folder / "blobs"), "UNDREAM_CACHE_DIR": str(folder / "cache"),
           "UNDREAM_FARM_SLOTS": "1"}
    env.pop("UNDREAM_SETTINGS", None)
    env.pop("UNDREAM_DATABASE_URL", None)
    cli = [sys.executable, "-m", "undream.cli"]
    log = open(folder / "worker.log", "w")
    worker = subprocess.Popen([*cli, "worker", "--concurrency", "1", "--threads", str(threads)], cwd=ROOT,
                              env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        end = time.monotonic() + 120
        while "ready." not in (folder / "worker.log").read_text():
            if worker.poll() is not None or time.monotonic() > end:
                raise RuntimeError("worker did not start:\n" + (folder / "worker.log").read_text()[-2000:])
            time.sleep(0.2)
        start = time.monotonic()
        res = subprocess.run([*cli, "submit", str(run_yaml), "--out", str(folder / "out")], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=600)
        if res.returncode != 0:
            raise RuntimeError(res.stderr)
        run_id = res.stdout.strip().splitlines()[-1]
        from undream.store import open_store

        store = open_store(None, folder / "blobs")
        try:
            while (status := store.get_run(run_id).status) not in ("done", "failed", "cancelled"):
                if time.monotonic() - start > timeout:
                    raise RuntimeError(f"run {run_id} still {status} after {timeout} s")
                time.sleep(0.5)
            if status != "done":
                raise RuntimeError(f"run {run_id} {status}: {store.get_run(run_id).error}")
        finally:
            store.close()
        wall = time.monotonic() - start
        kids = _children(worker.pid)
        if len(kids) != 1:
            raise RuntimeError(f"expected one worker child, found {kids}")
        return {"child_mib": _status_kib(kids[0], "VmHWM") / 1024,
                "parent_mib": _status_kib(worker.pid, "VmHWM") / 1024, "wall_s": wall}
    finally:
        os.killpg(worker.pid, signal.SIGKILL)
        worker.wait()
        log.close()


def measure_local(run_yaml: Path, folder: Path) -> float:
    """Peak RSS (MiB) of ``undream run`` on ``run_yaml``, measured by /usr/bin/time (GNU time, ``%M``)."""
    out = folder / "time.txt"
    res = subprocess.run(["/usr/bin/time", "-f", "%M", "-o", str(out), sys.executable, "-m", "undream.cli", "run",
                          str(run_yaml), "--out", str(folder / "local"), "--no-progress"], cwd=ROOT,
                         capture_output=True, text=True,
                         env={**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"})
    if res.returncode != 0:
        raise RuntimeError(res.stderr)
    return int(out.read_text().split()[-1]) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--px", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--frames", type=int, nargs="+", default=[8, 32])
    parser.add_argument("--steps", type=int, default=6, help="PGD steps (>= 6 includes a transport refresh)")
    parser.add_argument("--threads", type=int, default=2, help="Dr.Jit threads of the worker process")
    parser.add_argument("--broker", default="redis://127.0.0.1:6379/1")
    parser.add_argument("--local", action="store_true", help="also measure `undream run` (one process)")
    parser.add_argument("--timeout", type=float, default=900)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}", flush=True)
    print("| px | frames | steps | worker child peak RSS MiB | worker parent peak RSS MiB | submit → done s |"
          + (" `undream run` peak RSS MiB |" if args.local else ""), flush=True)
    for px in args.px:
        for frames in args.frames:
            with tempfile.TemporaryDirectory(prefix="undream-mem-") as tmp:
                folder = Path(tmp)
                run_yaml = write_inputs(folder, px, frames, args.steps)
                local = f" {measure_local(run_yaml, folder):.0f} |" if args.local else ""
                m = measure_worker(run_yaml, folder, args.broker, args.threads, args.timeout)
                print(f"| {px} | {frames} | {args.steps} | {m['child_mib']:.0f} | {m['parent_mib']:.0f} | "
                      f"{m['wall_s']:.1f} |{local}", flush=True)
    print(f"load average after: {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
