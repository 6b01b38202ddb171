#!/usr/bin/env python
"""The chaos soak: tiny farm runs under random faults, no person involved; print a table.

    .venv/bin/python benchmarks/chaos_soak.py [--runs 8] [--workers 3] [--kills 4] [--child-kills 2]
        [--pauses 2] [--broker-restarts 2] [--db-restarts 2] [--steps 20] [--interval 5] [--seed 0]

A private Redis (``redis-server`` on a free port, ``--save "" --appendonly no``: a restart loses
everything) and a private PostgreSQL (``initdb`` into a temporary folder and ``pg_ctl`` on a free
port, run as the ``postgres`` user when this runs as root, ``fsync=off``), blobs in a temporary
folder, ``--workers`` real ``undream worker`` processes (one process, one thread each) with the
farm's default settings (``heal_after`` 30 s, ``heal_interval`` 15 s, ``visibility_timeout``
3600 s) unless given. One ``undream sweep`` of ``--runs`` tiny runs (the farm tests' 4-frame
24 px sphere and tiny victim, PGD, seeds 0 … N−1). While runs are active, one fault every
``--interval`` seconds on average, in random order:

- ``kill``: SIGKILL a worker's process group (parent and pool process); a new worker starts
  ``--restart-after`` seconds later, as a supervisor would start it;
- ``child-kill``: SIGKILL a worker's pool process only (Celery starts another);
- ``pause``: SIGSTOP a worker's process group, SIGCONT 5–45 s later (past the 30 s its
  announcement lives, so the healer may send its work again: both copies finish);
- ``broker-restart``: SIGKILL Redis, start it again empty 1–3 s later;
- ``db-restart``: ``pg_ctl stop -m immediate`` (a crash), start again 1–5 s later.

The soak never runs ``undream resume``: what the faults stall the workers must heal. Then each
run's final texture (its output folder's ``texture_final.npy``) is compared byte for byte with
the same run's in-process reference (``undream run``'s code, :func:`scheduler.local.run_local`),
its iterations are checked (each k once), and the stalls are read from the store: a run's
*progress* is a job start or finish (any phase) and its creation; the longest time without
progress of any run, and for each heal (an event line ``healed: …``) the time from the run's
last progress to the heal. The machine's load is printed with the table.
"""
from __future__ import annotations

import argparse
import datetime as dt
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("kill", "child-kill", "pause", "broker-restart", "db-restart")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _as_postgres(argv: list[str]) -> list[str]:
    """``argv`` run as the ``postgres`` user when this process is root (initdb refuses root)."""
    return ["runuser", "-u", "postgres", "--", *argv] if os.geteuid() == 0 else argv


class Redis:
    """A private redis-server without persistence; :meth:`restart` empties it."""

    def __init__(self, root: Path) -> None:
        self.port, self.root, self.proc = free_port(), root, None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen(["redis-server", "--port", str(self.port), "--bind", "127.0.0.1",
                                      "--save", "", "--appendonly", "no", "--dir", str(self.root)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        _wait_port(self.port, 10, "redis-server")

    def restart(self, down_s: float) -> None:
        self.proc.kill()
        self.proc.wait()
        time.sleep(down_s)
        self.start()

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"


class Postgres:
    """A private PostgreSQL cluster in ``root`` (owned by ``postgres`` when run as root)."""

    def __init__(self, root: Path) -> None:
        bins = sorted(Path("/usr/lib/postgresql").glob("*/bin"))
        if not bins:
            raise SystemExit("chaos_soak: no /usr/lib/postgresql/*/bin (PostgreSQL's server programs)")
        self.bin, self.port, self.data = bins[-1], free_port(), root / "pgdata"
        root.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            shutil.chown(root, "postgres", "postgres")
            os.chmod(root.parent, 0o755)
        subprocess.run(_as_postgres([str(self.bin / "initdb"), "-D", str(self.data), "-U", "postgres",
                                     "--auth=trust", "-E", "UTF8"]), check=True, capture_output=True)
        opts = (f"-p {self.port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off "
                "-c max_connections=200")
        self.ctl = [str(self.bin / "pg_ctl"), "-D", str(self.data), "-o", opts, "-l", str(root / "pg.log")]
        self.start()
        subprocess.run(_as_postgres([str(self.bin / "createdb"), "-h", "127.0.0.1", "-p", str(self.port),
                                     "-U", "postgres", "farm"]), check=True, capture_output=True)

    def start(self) -> None:
        subprocess.run(_as_postgres([*self.ctl, "-w", "start"]), check=True, capture_output=True)

    def restart(self, down_s: float) -> None:
        subprocess.run(_as_postgres([*self.ctl, "-m", "immediate", "stop"]), check=True, capture_output=True)
        time.sleep(down_s)
        self.start()

    def stop(self) -> None:
        subprocess.run(_as_postgres([*self.ctl, "-m", "fast", "stop"]), capture_output=True)

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/farm"


def _wait_port(port: int, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise SystemExit(f"chaos_soak: {what} did not listen on port {port} within {timeout} s")


@dataclass
class Slot:
    """One worker place: its process (None while down), and when to start or continue it."""

    proc: subprocess.Popen | None = None
    start_at: float | None = None  # a killed worker's replacement starts then
    cont_at: float | None = None  # a paused worker continues then


@dataclass
class Farm:
    root: Path
    env: dict[str, str]
    slots: list[Slot] = field(default_factory=list)
    started: int = 0

    def start(self, slot: Slot) -> None:
        log = open(self.root / f"worker{self.started}.log", "w")
        self.started += 1
        slot.proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "worker", "--concurrency", "1",
                                      "--threads", "1"], cwd=ROOT, env=self.env, stdout=log,
                                     stderr=subprocess.STDOUT, start_new_session=True)
        slot.start_at = slot.cont_at = None

    def tend(self, now: float) -> None:
        """Start the replacements and continue the paused workers that are due."""
        for slot in self.slots:
            if slot.cont_at is not None and now >= slot.cont_at and slot.proc is not None:
                _signal_group(slot.proc, signal.SIGCONT)
                slot.cont_at = None
            if slot.proc is None and slot.start_at is not None and now >= slot.start_at:
                self.start(slot)

    def running(self) -> list[Slot]:
        return [s for s in self.slots if s.proc is not None and s.cont_at is None]

    def stop(self) -> None:
        for slot in self.slots:
            if slot.proc is not None:
                _signal_group(slot.proc, signal.SIGCONT)
                _signal_group(slot.proc, signal.SIGTERM)
        for slot in self.slots:
            if slot.proc is not None:
                try:
                    slot.proc.wait(20)
                except subprocess.TimeoutExpired:
                    _signal_group(slot.proc, signal.SIGKILL)
                    slot.proc.wait(10)


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def inject(kind: str, farm: Farm, redis: Redis, pg: Postgres, rng: random.Random, args: argparse.Namespace,
           now: float) -> bool:
    """One fault of ``kind``; False when there is nothing to hit now (no running worker, no pool process)."""
    if kind == "broker-restart":
        redis.restart(rng.uniform(1, 3))
        return True
    if kind == "db-restart":
        pg.restart(rng.uniform(1, 5))
        return True
    live = farm.running()
    if not live:
        return False
    slot = rng.choice(live)
    if kind == "kill":
        _signal_group(slot.proc, signal.SIGKILL)
        slot.proc.wait(10)
        slot.proc, slot.start_at = None, now + args.restart_after
    elif kind == "child-kill":
        children = _children(slot.proc.pid)
        if not children:
            return False
        os.kill(rng.choice(children), signal.SIGKILL)
    else:
        _signal_group(slot.proc, signal.SIGSTOP)
        slot.cont_at = now + rng.uniform(5, 45)
    return True


def _utc(t: dt.datetime) -> dt.datetime:
    return t if t.tzinfo is not None else t.replace(tzinfo=dt.timezone.utc)


def stalls(store: Any, run: Any) -> tuple[float, list[float]]:
    """The run's longest time without progress (s), and for each heal the time from its last
    progress to the heal (s)."""
    times = [_utc(run.created)]
    for phase in ("attack", "pre", "adversarial"):
        for job in store.jobs(run.id, None, phase):
            times += [_utc(t) for t in (job.started, job.finished) if t is not None]
    times.sort()
    longest = max((b - a).total_seconds() for a, b in zip(times, times[1:])) if len(times) > 1 else 0.0
    heals = []
    for event in store.events(run.id):
        if event.line.startswith("healed: "):
            at = _utc(event.time)
            before = [t for t in times if t <= at]
            heals.append((at - before[-1]).total_seconds() if before else 0.0)
    return longest, heals


def asked(args: argparse.Namespace) -> Counter[str]:
    """The faults asked for, by kind."""
    return Counter(dict(zip(KINDS, (args.kills, args.child_kills, args.pauses, args.broker_restarts,
                                    args.db_restarts))))


def drive(farm: Farm, store: Any, redis: Redis, pg: Postgres, rng: random.Random, args: argparse.Namespace,
          t0: float) -> Counter[str]:
    """Inject the faults, in random order, while runs are active; return once no run is active
    and no worker is paused (or after ``--timeout``). Returns the faults injected, by kind."""
    faults = list(asked(args).elements())
    rng.shuffle(faults)
    done: Counter[str] = Counter()
    next_fault, active = time.monotonic() + rng.uniform(0.5, 1.5) * args.interval, args.runs
    while time.monotonic() - t0 < args.timeout:
        now = time.monotonic()
        farm.tend(now)
        if faults and now >= next_fault and active:
            kind = faults[0]
            if inject(kind, farm, redis, pg, rng, args, now):
                done[faults.pop(0)] += 1
                print(f"{now - t0:7.1f} s  fault {sum(done.values()):3d}: {kind:14s} {active} runs active", flush=True)
            next_fault = time.monotonic() + rng.uniform(0.5, 1.5) * args.interval
        try:
            counts = store.status_counts(None)
            active = sum(counts.get(s, 0) for s in ("queued", "running", "evaluating"))
        except Exception:  # the database restarting: ask again next round
            pass
        if not active and all(s.cont_at is None for s in farm.slots):
            break  # faults not injected yet are reported as such: give the runs more --steps
        time.sleep(0.5)
    return done


def soak(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """Services, workers, the sweep, the faults, then :func:`check`; the numbers of the table."""
    import yaml

    sys.path.insert(0, str(ROOT / "tests"))
    from farm_support import make_scene, make_victim, run_config
    from undream.store import open_store

    rng = random.Random(args.seed)
    scene, victim = make_scene(tmp / "scene", n_frames=4, size=24), make_victim(tmp / "victim")
    base = run_config(scene, victim, name="soak", steps=args.steps, sim_spp=args.sim_spp, grad_spp=4)
    (tmp / "run.yaml").write_text(yaml.safe_dump(base))
    (tmp / "sweep.yaml").write_text(yaml.safe_dump({"name": "soak", "run": str(tmp / "run.yaml"),
                                                    "grid": {"seed": list(range(args.runs))}}))
    redis = Redis(tmp)
    pg = farm = None
    try:
        pg = Postgres(tmp / "pg")
        env = {**os.environ, "PYTHONPATH": str(ROOT), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1",
               "PYTHONUNBUFFERED": "1", "UNDREAM_BROKER_URL": redis.url, "UNDREAM_DATABASE_URL": pg.url,
               "UNDREAM_BLOB_URL": str(tmp / "blobs"), "UNDREAM_CACHE_DIR": str(tmp / "cache"),
               "UNDREAM_FARM_SLOTS": str(args.workers)}
        env.pop("UNDREAM_SETTINGS", None)
        for name in ("heal_after", "heal_interval", "visibility_timeout"):
            if getattr(args, name) is not None:
                env[f"UNDREAM_{name.upper()}"] = str(getattr(args, name))
        farm = Farm(tmp, env, [Slot() for _ in range(args.workers)])
        load0, t0 = os.getloadavg(), time.monotonic()
        for slot in farm.slots:
            farm.start(slot)
        res = subprocess.run([sys.executable, "-m", "undream.cli", "sweep", str(tmp / "sweep.yaml")], cwd=ROOT,
                             env=env, capture_output=True, text=True, timeout=600)
        if res.returncode != 0:
            raise SystemExit(f"chaos_soak: undream sweep failed: {res.stderr.strip()}")
        print(f"{time.monotonic() - t0:7.1f} s  {args.runs} runs submitted", flush=True)
        with open_store(pg.url, tmp / "blobs") as store:
            done = drive(farm, store, redis, pg, rng, args, t0)
            wall, load1 = time.monotonic() - t0, os.getloadavg()
            results = check(store, store.runs(), base, tmp, args)
    finally:
        if farm is not None:
            farm.stop()
        redis.stop()
        if pg is not None:
            pg.stop()
    return {**results, "faults": done, "asked": asked(args), "wall": wall, "load0": load0, "load1": load1,
            "workers_started": farm.started}


def check(store: Any, runs: list[Any], base: dict[str, Any], tmp: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Each run's texture against its in-process reference, its iterations, its stalls and heals."""
    import numpy as np

    from scheduler.local import run_local
    from scheduler.outputs import default_out_dir
    from undream.spec.run import RunConfig

    identical, bad_iterations, longest, heals, reasons = 0, [], 0.0, [], Counter()
    for run in runs:
        if run.status == "done":
            ref = tmp / "reference" / f"seed{run.seed}"
            run_local(RunConfig.from_json({**base, "seed": run.seed}), ref, progress=False)
            out = Path(run.out_dir) if run.out_dir else default_out_dir(store, run)
            identical += (np.load(out / "texture_final.npy").tobytes()
                          == np.load(ref / "texture_final.npy").tobytes())
            if [r.k for r in store.iterations(run.id)] != list(range(args.steps)):
                bad_iterations.append(run.id[:8])
        stall, healed = stalls(store, run)
        longest = max(longest, stall)
        heals += healed
        whys = [e.line.split("; sent again")[0] for e in store.events(run.id) if e.line.startswith("healed: ")]
        reasons.update(why[why.rfind("(") + 1:why.rfind(")")] for why in whys)  # "no live worker holds them"
    return {"runs": len(runs), "done": sum(r.status == "done" for r in runs),
            "failed": [(r.id[:8], r.status, r.error) for r in runs if r.status != "done"],
            "identical": identical, "bad_iterations": bad_iterations, "longest_stall": longest,
            "heals": heals, "reasons": reasons}


def table(r: dict[str, Any]) -> str:
    faults = ", ".join(f"{r['faults'][k]} {k}" + (f" (of {r['asked'][k]} asked)" if r['faults'][k] < r['asked'][k]
                                                   else "") for k in KINDS)
    worst_heal = max(r["heals"], default=0.0)
    rows = [
        ("runs done", f"{r['done']} of {r['runs']}"),
        ("manual steps (`undream resume`)", "0 (the soak never runs one)"),
        ("textures byte-identical to in-process `undream run`", f"{r['identical']} of {r['done']} done"),
        ("runs with an iteration missing or twice", str(len(r["bad_iterations"]))),
        ("faults injected", faults),
        ("heals (event lines)", f"{len(r['heals'])}: "
         + ", ".join(f"{n} {why}" for why, n in r["reasons"].most_common())
         if r["heals"] else "0"),
        ("longest stall healed (last progress → heal)", f"{worst_heal:.0f} s"),
        ("longest time any run made no progress", f"{r['longest_stall']:.0f} s"),
        ("workers started (replacements included)", str(r["workers_started"])),
        ("wall", f"{r['wall']:.0f} s"),
        ("load average (1, 5, 15 min) before / after", " / ".join(", ".join(f"{x:.2f}" for x in load)
                                                                  for load in (r["load0"], r["load1"]))),
    ]
    lines = ["| | |", "|---|---|", *(f"| {a} | {b} |" for a, b in rows)]
    if r["failed"]:
        lines.append("\nnot done: " + "; ".join(f"{i} {s}: {e}" for i, s, e in r["failed"]))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=8, help="runs of the sweep (default 8)")
    parser.add_argument("--workers", type=int, default=3, help="undream worker processes (default 3)")
    parser.add_argument("--steps", type=int, default=20, help="PGD iterations per run (default 20)")
    parser.add_argument("--sim-spp", type=int, default=16, help="samples per pixel of a frame job (default 16)")
    for kind, default in zip(KINDS, (4, 2, 2, 2, 2)):
        parser.add_argument(f"--{kind}s", type=int, default=default, help=f"{kind} faults (default {default})")
    parser.add_argument("--interval", type=float, default=5.0, help="mean seconds between faults (default 5)")
    parser.add_argument("--restart-after", type=float, default=2.0, help="s before a killed worker's replacement")
    parser.add_argument("--heal-after", type=int, default=None, help="the farm's heal_after (default: its default)")
    parser.add_argument("--heal-interval", type=int, default=None)
    parser.add_argument("--visibility-timeout", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0, help="seed of the faults' order, targets and times")
    parser.add_argument("--timeout", type=float, default=3600, help="s before the soak gives up waiting")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder (logs, store)")
    args = parser.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="undream-chaos-"))
    try:
        result = soak(args, tmp)
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            print(f"kept {tmp}")
    print(f"\n{' '.join(sys.argv)}\n{args.runs} runs × {args.steps} PGD steps "
          f"(4-frame 24 px sphere, sim_spp {args.sim_spp}), "
          f"{args.workers} workers, seed {args.seed}, {os.cpu_count()} cores\n")
    print(table(result))
    ok = (result["done"] == result["runs"] == result["identical"] and not result["bad_iterations"])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
