"""Shared pieces of the farm tests: a tiny victim and scene, real worker subprocesses, services.

The farm tests use the real Redis (``UNDREAM_TEST_REDIS``, default
127.0.0.1:6379; each farm on its own database number, flushed, claimed across
processes so that pytest-xdist's workers and other sessions never share one)
and the real PostgreSQL of tests/test_store.py (a fresh database per farm). A
farm whose test SIGKILLs the broker gets a Redis server of its own
(:class:`PrivateRedis`) instead: the machine's Redis is never killed. A
missing service is a skip that says why, never a silent pass.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REDIS_HOST = os.environ.get("UNDREAM_TEST_REDIS", "127.0.0.1:6379")
PG_ADMIN_URL = os.environ.get("UNDREAM_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
LABELS = ["car", "sphere", "stop_sign", "traffic_cone", "trash_bin", "umbrella"]
_used_dbs: set[int] = set()
DB_CLAIM = "undream-tests:redis-db:"  # + a number: a key in database 0 saying a farm of some session uses it


def make_victim(path: Path) -> str:
    """A tiny random HF ResNet over the built-in classes, saved locally (no network)."""
    import torch
    import transformers as T

    torch.manual_seed(0)
    cfg = T.ResNetConfig(embedding_size=8, hidden_sizes=[8, 16], depths=[1, 1],
                         id2label=dict(enumerate(LABELS)), label2id={n: i for i, n in enumerate(LABELS)})
    T.ResNetForImageClassification(cfg).save_pretrained(path)
    (path / "preprocessor_config.json").write_text(json.dumps(
        {"size": {"height": 32, "width": 32}, "do_normalize": True,
         "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]}))
    return str(path)


def cuda_driver_present() -> bool:
    """Whether this machine has an NVIDIA driver (libcuda) that Mitsuba's cuda_ad_rgb could load."""
    import ctypes

    try:
        ctypes.CDLL("libcuda.so.1")
        return True
    except OSError:
        return False


def make_scene(path: Path, n_frames: int = 4, size: int = 24) -> Path:
    """A sphere seen from ``n_frames`` cameras at ``size`` px, a 16×8 texture."""
    from undream.scene.poses import look_at
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

    angles = np.linspace(0.0, 1.5, n_frames)
    frames = tuple(Frame(i, Camera(Transform.from_rows(look_at([1.6 * np.sin(a), 1.2, 2.4 * np.cos(a)],
                                                               [0, 0.5, 0])), 40.0, (size, size)),
                         Transform.identity(), Environment("cloudy", 12.0)) for i, a in enumerate(angles))
    seq = Sequence("farm", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    return init_scene(seq, path, InitOptions(verify_spp=1))


def run_config(scene: Path, victim: str, name: str = "farm", steps: int = 3, **extra: Any) -> dict[str, Any]:
    attack = {"name": "pgd", "eps": 32.0, "steps": steps, **extra.pop("attack", {})}
    return {"scene": str(scene), "name": name, "victim": victim, "loss": "ce", "attack": attack,
            "sim_spp": 2, "grad_spp": 2, "eval_spp": 2, "seed": 5, **extra}


def eager_run(cfg: Any, root: Path) -> tuple[Any, str]:
    """``cfg`` (a RunConfig) recorded and run through the Celery app in eager mode (a logic test of the
    farm's path: tasks run in this process, nothing serialized), its outputs in ``root / "out"``:
    the open store (the caller closes it) and the run's id."""
    from scheduler.submit import Validator, record
    from undream.settings import load_settings
    from undream.store import open_store
    from workers.app import create_celery_app
    from workers.dispatch import CeleryDispatch

    settings = load_settings(env={}, broker_url="memory://", result_backend="cache+memory://",
                             blob_url=str(root / "blobs"), cache_dir=str(root / "cache"))
    app = create_celery_app(settings)
    app.conf.task_always_eager = True
    app.conf.task_eager_propagates = True
    store = open_store(settings.database_url, settings.blob_url)
    (run_id,) = record(store, [Validator(root / "work")(cfg, Path("."))], settings, root / "out")
    CeleryDispatch(app).start(run_id)
    return store, run_id


def write_yaml(path: Path, data: dict[str, Any]) -> Path:
    import yaml

    path.write_text(yaml.safe_dump(data))
    return path


def runs_per_attack_value(tmp_path: Path, scene: Path, victim: str, field: str,
                          values: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Through `undream run` (a process each): the same tiny run once per value of ``attack.<field>``,
    asserting each exits 0 and keeps the value in its results.json; each run's final texture by value."""
    textures = {}
    for value in values:
        cfg = run_config(scene, victim, name=f"{field}_{value}", steps=3, holdout="none", attack={field: value})
        out = tmp_path / f"{field}_{value}"
        res = subprocess.run([sys.executable, "-m", "undream.cli", "run",
                              str(write_yaml(tmp_path / f"{field}_{value}.yaml", cfg)), "--out", str(out),
                              "--no-progress"], capture_output=True, text=True, cwd=ROOT)
        assert res.returncode == 0, res.stderr
        assert json.loads((out / "results.json").read_text())["attack"][field] == value
        textures[value] = np.load(out / "texture_final.npy")
    return textures


def claim_during_preflight(monkeypatch: Any, module: Any, out: Path, winner: dict[str, str]) -> None:
    """Make a command's output race deterministic: when ``module.preflight`` has checked (and seen no
    ``out``), another command claims ``out`` and writes ``winner`` (relative path → text) into it."""
    real = module.preflight

    def preflight_while_another_claims(*args: Any, **kwargs: Any) -> Any:
        checked = real(*args, **kwargs)
        assert not out.exists()  # this command's check saw no folder
        for name, text in winner.items():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            (out / name).write_text(text)
        return checked

    monkeypatch.setattr(module, "preflight", preflight_while_another_claims)


def redis_client(db: int = 0, server: str = REDIS_HOST):
    import redis

    host, port = server.split(":")
    return redis.Redis(host=host, port=int(port), db=db, socket_connect_timeout=2)


def redis_up() -> str | None:
    """None when Redis answers, else why not."""
    try:
        redis_client().ping()
        return None
    except Exception as exc:
        return f"Redis unreachable at {REDIS_HOST}: {exc}"


class PrivateRedis:
    """A ``redis-server`` of its own on a free loopback port (no persistence, its files in ``root``),
    for a test that SIGKILLs the broker mid-run and starts it again, empty, on the same port: the
    machine's Redis, which other farms (of this session's xdist workers or of other sessions) use,
    stays up."""

    def __init__(self, root: Path) -> None:
        from conftest import free_port, service_missing

        if shutil.which("redis-server") is None:
            service_missing("redis-server not found (apt-get install redis-server)")
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.host = f"127.0.0.1:{free_port()}"
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        """Start the server (again, after :meth:`kill`) and wait until it answers."""
        port = self.host.split(":")[1]
        log = self.root / "redis.log"
        with log.open("a") as out:
            self.proc = subprocess.Popen(["redis-server", "--bind", "127.0.0.1", "--port", port, "--save", "",
                                          "--appendonly", "no", "--dir", str(self.root)],
                                         stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        wait_for(lambda: self.up() or self.proc.poll() is not None, 20, f"a private Redis on {self.host}")
        assert self.proc.poll() is None, log.read_text()[-2000:]

    def client(self, db: int = 0):
        return redis_client(db, self.host)

    def up(self) -> bool:
        try:
            return bool(self.client().ping())
        except Exception:  # redis' ConnectionError or a timeout: not up
            return False

    def kill(self) -> None:
        """SIGKILL the server (by the pid it reports, as an operator's ``kill -9`` would) and wait until
        it no longer answers."""
        os.kill(self.client().info("server")["process_id"], signal.SIGKILL)
        self.proc.wait(10)
        wait_for(lambda: not self.up(), 10, "the private Redis to go away")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def free_db() -> int:
    """A Redis database number no other farm uses, of this test session or of another one running
    beside it on this machine (claimed by a key in database 0 holding the claiming process's pid,
    which lapses after an hour; a claim whose process is gone is taken over), flushed."""
    claims = redis_client(0)
    for db in range(15, 0, -1):
        if db in _used_dbs:
            continue
        key = f"{DB_CLAIM}{db}"
        holder = claims.get(key)
        if holder is not None and not _gone(holder):
            continue
        if holder is not None:
            claims.delete(key)  # its session died without giving it back
        if claims.set(key, os.getpid(), nx=True, ex=3600):
            _used_dbs.add(db)
            redis_client(db).flushdb()
            return db
    raise RuntimeError("no free Redis database number (each is claimed by a farm of a live test session)")


def _gone(pid: bytes) -> bool:
    """Whether the process ``pid`` (a claim's value) no longer runs on this machine."""
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except (ValueError, PermissionError):
        return False
    return False


def release_db(db: int) -> None:
    """Flush database ``db`` and give its number back (its workers are gone)."""
    if db in _used_dbs:
        redis_client(db).flushdb()
        _used_dbs.discard(db)
        redis_client(0).delete(f"{DB_CLAIM}{db}")


class Farm:
    """One farm: its settings as environment variables, its worker subprocesses, its CLI."""

    def __init__(self, root: Path, database_url: str | None = None, blob_url: str | None = None,
                 redis: PrivateRedis | None = None, **settings: Any) -> None:
        self.root = root
        self.private_redis = redis  # None: a claimed database of the machine's Redis
        self.db = 0 if redis is not None else free_db()
        self.broker = f"redis://{redis.host if redis is not None else REDIS_HOST}/{self.db}"
        self.blobs = root / "blobs"
        # Blobs in the database or S3: each worker gets its own cache and temporary folders (no
        # folder is shared between the farm's processes, as on a cluster without a shared volume).
        self.own_folders = blob_url is not None
        self.env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1",
                    "UNDREAM_BROKER_URL": self.broker, "UNDREAM_BLOB_URL": blob_url or str(self.blobs),
                    "UNDREAM_CACHE_DIR": str(root / "cache"), "UNDREAM_VISIBILITY_TIMEOUT": "12",
                    "UNDREAM_RESTORE_INTERVAL": "1", "PYTHONUNBUFFERED": "1"}
        self.env.pop("UNDREAM_SETTINGS", None)
        if database_url:
            self.env["UNDREAM_DATABASE_URL"] = database_url
        self.env.update({f"UNDREAM_{k.upper()}": str(v) for k, v in settings.items()})
        self.workers: list[subprocess.Popen] = []
        self._store = None

    def settings(self):
        from undream.settings import load_settings
        return load_settings(env=self.env)

    @property
    def store(self):
        from undream.store import open_farm_store

        if self._store is None:
            self._store = open_farm_store(self.settings())
        return self._store

    def cli(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "undream.cli", *args], capture_output=True, text=True,
                              cwd=ROOT, env=self.env, timeout=timeout)

    def submit(self, run_yaml: Path, *extra: str) -> str:
        res = self.cli("submit", str(run_yaml), *extra)
        assert res.returncode == 0, res.stderr
        return res.stdout.strip().splitlines()[-1]

    def start_worker(self, concurrency: int = 1, threads: int = 1) -> subprocess.Popen:
        """An ``undream worker`` in its own process group; waits until it consumes."""
        n = len(self.workers)
        log = open(self.root / f"worker{n}.log", "w")
        env = self.env
        if self.own_folders:
            (self.root / f"tmp{n}").mkdir()
            env = {**env, "UNDREAM_CACHE_DIR": str(self.root / f"cache{n}"), "TMPDIR": str(self.root / f"tmp{n}")}
        proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "worker", "--concurrency",
                                 str(concurrency), "--threads", str(threads)], cwd=ROOT, env=env,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.workers.append(proc)
        path = Path(log.name)
        wait_for(lambda: "ready." in path.read_text() or proc.poll() is not None, 60, "worker ready")
        assert proc.poll() is None, path.read_text()[-3000:]
        return proc

    def kill_worker(self, proc: subprocess.Popen) -> None:
        """SIGKILL the worker and its children (its process group)."""
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(10)

    def stop(self) -> None:
        stop_workers(self.workers)
        self.workers.clear()
        if self._store is not None:
            self._store.close()
            self._store = None
        if self.private_redis is None:
            release_db(self.db)  # its workers are gone: the number is free for the next farm

    def logs(self) -> str:
        return "\n".join(p.read_text()[-4000:] for p in sorted(self.root.glob("worker*.log")))

    def wait_status(self, run_id: str, statuses: tuple[str, ...] = ("done",), timeout: float = 90) -> Any:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            run = self.store.get_run(run_id)
            if run.status in statuses:
                return run
            if run.status in ("failed", "cancelled") and run.status not in statuses:
                raise AssertionError(f"run {run_id} {run.status}: {run.error}\n{self.logs()}")
            time.sleep(0.2)
        raise AssertionError(f"run {run_id} still {self.store.get_run(run_id).status} after {timeout} s\n"
                             f"{self.logs()}")


def wait_for(cond: Callable[[], Any], timeout: float, what: str, interval: float = 0.1) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = cond()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def stop_workers(procs: list[subprocess.Popen], wait_s: float = 10) -> None:
    """SIGTERM each worker's process group (a worker finishes its job), SIGKILL one still there after ``wait_s``."""
    for proc in procs:
        if proc.poll() is not None:
            continue
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(wait_s)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def finished_runs(store: Any, n: int) -> list[Any] | None:
    """The ``n`` newest runs once every one is done, failed or cancelled, else None (for :func:`wait_for`)."""
    runs = store.runs_page(limit=n).runs
    return runs if runs and all(r.status in ("done", "failed", "cancelled") for r in runs) else None


@contextlib.contextmanager
def sql_statements() -> Iterator[list[str]]:
    """Every SQL statement any engine of this process executes inside the block."""
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    seen: list[str] = []

    def count(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
        seen.append(statement)

    event.listen(Engine, "before_cursor_execute", count)
    try:
        yield seen
    finally:
        event.remove(Engine, "before_cursor_execute", count)


def postgres_database(admin_url: str) -> tuple[str, Callable[[], None]]:
    """A fresh PostgreSQL database: its URL and a function that drops it."""
    from sqlalchemy import create_engine, text

    engine = create_engine(admin_url, isolation_level="AUTOCOMMIT", connect_args={"connect_timeout": 3})
    name = f"undream_farm_{uuid.uuid4().hex[:12]}"
    with engine.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))

    def drop() -> None:
        with engine.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        engine.dispose()

    return engine.url.set(database=name).render_as_string(hide_password=False), drop


def fresh_postgres(admin_url: str = PG_ADMIN_URL) -> tuple[str, Callable[[], None]]:
    """:func:`postgres_database`, or a skip saying why there is none (a failure under
    ``UNDREAM_REQUIRE_SERVICES``, see tests/conftest.py)."""
    import pytest

    from conftest import service_missing

    pytest.importorskip("psycopg", reason="psycopg not installed (pip install 'undream[postgres]')")
    try:
        return postgres_database(admin_url)
    except Exception as exc:  # the server is down: sqlalchemy's or psycopg's error
        service_missing(f"PostgreSQL unreachable at {admin_url}: {str(exc).splitlines()[0]}")
        raise  # not reached: service_missing skips or fails


def farm_inputs(tmp_path_factory, name: str, n_frames: int) -> dict:
    """A tiny victim and an ``n_frames`` scene for farm tests; Redis must answer."""
    from conftest import service_missing

    reason = redis_up()
    if reason:
        service_missing(reason)
    root = tmp_path_factory.mktemp(name)
    return {"root": root, "victim": make_victim(root / "victim"), "scene": make_scene(root / "scene", n_frames)}
