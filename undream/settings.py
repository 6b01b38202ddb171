"""The farm's settings: one object built from defaults → settings file → ``UNDREAM_*`` environment → flags.

Every farm process (``undream submit``, ``undream worker``, ``status``, ...)
builds one :class:`Settings` with :func:`load_settings` and passes it
explicitly; nothing reads the environment later. A settings file is YAML
with the field names below (``--settings FILE`` or ``$UNDREAM_SETTINGS``)::

    broker_url: redis://farm-head:6379/0
    database_url: postgresql://undream:secret@farm-head:5432/undream
    blob_url: /mnt/shared/undream          # a folder every machine mounts, or
    # blob_url: database                   # blobs in the run database (database_url must be set)
    # blob_url: s3://undream-farm/blobs    # S3-compatible object storage (s3_* below)
    s3_endpoint_url: http://minio:9000     # unset: AWS
    drjit_threads: 1

Environment: ``UNDREAM_`` + the field name in capitals (``UNDREAM_BROKER_URL``,
``UNDREAM_RESULT_BACKEND``, ``UNDREAM_DATABASE_URL``, ``UNDREAM_BLOB_URL``,
``UNDREAM_CACHE_DIR``, ``UNDREAM_DRJIT_THREADS``, ``UNDREAM_DASHBOARD_TOKEN``, ...).
Errors name the source (file and field, or variable) and the value (never a token's).
The S3 settings also take the usual AWS variables where no ``UNDREAM_S3_*``
variable or file sets them: ``AWS_ENDPOINT_URL_S3`` (or ``AWS_ENDPOINT_URL``),
``AWS_REGION`` (or ``AWS_DEFAULT_REGION``), ``AWS_ACCESS_KEY_ID`` and
``AWS_SECRET_ACCESS_KEY``; the keys are secrets and never shown.

Every command (``init``, ``run``, ``baseline``, ...) and every worker process
also builds one :class:`LocalSettings` with :func:`load_local`: how this
process renders and loads, from these variables (read here and nowhere else
in the library)::

    UNDREAM_MI_VARIANT       the Mitsuba variant (default: cuda_ad_rgb if it works, else llvm_ad_rgb)
    UNDREAM_FROZEN           0: no Dr.Jit frozen functions for the simulator's renders (default 1)
    UNDREAM_MEMORY_LIMIT     bytes a render may use (K/M/G/T suffix; default: MemAvailable)
    UNDREAM_BLENDER_PYTHON   the interpreter that has bpy (default <repo>/.venv-blender/bin/python)
    UNDREAM_BLENDER_THREADS  Cycles' CPU threads (default: the process's Dr.Jit threads)
    UNDREAM_UNREAL_SPOOL     the spool folder shared with the Unreal editor's worker
    UNDREAM_UNREAL_TIMEOUT   seconds to wait for one Unreal frame (default 600)
    UNDREAM_BENIGN_CACHE     0: every run renders and judges its benign frames itself (default 1:
                             read them where a run with the same key kept them; scheduler.benign)
    HF_HUB_OFFLINE, TRANSFORMERS_OFFLINE   1/true/yes/on: never ask the Hugging Face hub

Other tools' variables, read to find things: ``XDG_DATA_HOME`` and
``XDG_CACHE_HOME`` (default folders), ``DRJIT_LIBCUDA_PATH`` (the CUDA driver
Dr.Jit loads), ``CUDA_VISIBLE_DEVICES`` (named when no GPU is visible). The
environment handed to Blender's interpreter is :attr:`LocalSettings.child_env`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, fields
from pathlib import Path
import re
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec.io import read_yaml

ENV_PREFIX = "UNDREAM_"
SETTINGS_ENV = "UNDREAM_SETTINGS"


class SettingsError(SpecError):
    """A setting is missing or invalid (the message names where it came from)."""


def data_home(env: Mapping[str, str] | None = None) -> Path:
    """``$XDG_DATA_HOME`` of ``env`` (default ``os.environ``), else ``~/.local/share``."""
    env = os.environ if env is None else env
    return Path(env.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")


def cache_home(env: Mapping[str, str] | None = None) -> Path:
    """``$XDG_CACHE_HOME`` of ``env`` (default ``os.environ``), else ``~/.cache``."""
    env = os.environ if env is None else env
    return Path(env.get("XDG_CACHE_HOME") or Path.home() / ".cache")


@dataclass(frozen=True)
class Settings:
    """Where the farm's broker, database and blobs are, and how workers run.

    ``database_url`` None: SQLite in the blob folder (one machine).
    ``result_backend`` None: the broker's Redis. ``frames_per_task`` None:
    ``ceil(frames / farm_slots)``, so an iteration is one task per worker
    slot (see the README, "Farm"). ``drjit_threads`` None: Dr.Jit's
    default (every core) — give each worker process its share.
    """

    broker_url: str = "redis://127.0.0.1:6379/0"
    result_backend: str | None = None
    database_url: str | None = None
    blob_url: str = ""  # "" → $XDG_DATA_HOME/undream/farm
    cache_dir: str = ""  # "" → $XDG_CACHE_HOME/undream (unpacked scenes, per machine)
    concurrency: int = 1  # worker processes per `undream worker`
    drjit_threads: int | None = None  # Dr.Jit threads per worker process
    torch_threads: int = 1  # the victim's threads per worker process
    frames_per_task: int | None = None  # frames rendered by one task (None: auto)
    farm_slots: int = 2  # worker processes the farm has in all (for the auto frames_per_task)
    max_attempts: int = 3  # attempts per frame job (retries included), then the job fails
    failure_budget: int = 2  # failed frame jobs a run survives (each re-queued), then it fails
    store_retries: int = 10  # retries of a task whose database or blob folder failed, then its run fails
    visibility_timeout: int = 3600  # s; a job unacknowledged this long is delivered again (> the longest task)
    restore_interval: int = 10  # s between sweeps that re-deliver jobs of lost workers
    heal_after: int = 30  # s a farm run held by no live worker may make no progress before it is sent again (0: never)
    heal_interval: int = 15  # s between the workers' checks for such runs (one worker checks at a time)
    # s between a worker's announcements in Redis; a worker silent 3x this long is taken for gone and
    # its work sent again by the healer. Every process of a farm must use the same value.
    worker_beat: int = 10
    scene_cache: int = 2  # scene directories whose Mitsuba scenes a worker process keeps loaded
    connect_timeout: float = 5.0  # s to reach the broker before giving up (CLI commands)
    dashboard_token: str | None = field(default=None, repr=False)  # cancel/resume need it; None: none
    transport_cache_mb: int = 512  # MB of captured transports the blob store keeps (least recently used go)
    benign_cache: bool = True  # runs read a benign evaluation another run computed (scheduler.benign)
    s3_endpoint_url: str | None = None  # S3-compatible endpoint of s3:// blobs (None: AWS)
    s3_region: str | None = None  # its region (None: boto3's default)
    s3_access_key_id: str | None = field(default=None, repr=False)  # None: boto3's own credential chain
    s3_secret_access_key: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        for name in ("broker_url",):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise SettingsError(f"{name}: must be a non-empty URL, got {getattr(self, name)!r}")
        for name in ("result_backend", "database_url"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, str) or not value):
                raise SettingsError(f"{name}: must be a URL or unset, got {value!r}")
        if self.backend_url.split("://")[0] not in ("redis", "rediss", "memory", "cache+memory"):
            raise SettingsError(f"result_backend: {self.backend_url.split('://')[0]}:// cannot hold the "
                                "chords' results; give a Redis URL (redis://host:6379/0)")
        if not self.blob_url:
            object.__setattr__(self, "blob_url", str(data_home() / "undream" / "farm"))
        if not self.cache_dir:
            object.__setattr__(self, "cache_dir", str(cache_home() / "undream"))
        for name, least in (("concurrency", 1), ("torch_threads", 1), ("farm_slots", 1),
                            ("max_attempts", 1), ("failure_budget", 0), ("store_retries", 0),
                            ("visibility_timeout", 1),
                            ("restore_interval", 1), ("scene_cache", 1), ("transport_cache_mb", 0),
                            ("heal_after", 0), ("heal_interval", 1), ("worker_beat", 1)):
            _check_int(name, getattr(self, name), least)
        for name in ("drjit_threads", "frames_per_task"):
            if getattr(self, name) is not None:
                _check_int(name, getattr(self, name), 1)
        for name in ("s3_endpoint_url", "s3_region", "s3_access_key_id", "s3_secret_access_key"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, str) or not value):
                shown = repr(value) if name in ("s3_endpoint_url", "s3_region") else "a value that is not text"
                raise SettingsError(f"{name}: must be text or unset, got {shown}")
        token = self.dashboard_token
        if token is not None and (not isinstance(token, str) or len(token.strip()) < 8):
            raise SettingsError("dashboard_token: must be a secret of at least 8 characters or unset, "
                                f"got {'a shorter one' if isinstance(token, str) else repr(token)}")
        if not isinstance(self.benign_cache, bool):
            raise SettingsError(f"benign_cache: must be true or false, got {self.benign_cache!r}")
        if isinstance(self.connect_timeout, bool) or not isinstance(self.connect_timeout, (int, float)) \
                or not self.connect_timeout > 0:
            raise SettingsError(f"connect_timeout: must be a number of seconds > 0, got {self.connect_timeout!r}")

    @property
    def backend_url(self) -> str:
        """The Celery result backend (the broker's Redis unless set)."""
        return self.result_backend or self.broker_url

    def frames_per_task_for(self, n_frames: int) -> int:
        """Frames per task for a run of ``n_frames`` frames (see the class docstring)."""
        if self.frames_per_task is not None:
            return self.frames_per_task
        return max(1, -(-n_frames // self.farm_slots))


def _check_int(name: str, value: Any, least: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise SettingsError(f"{name}: must be an integer >= {least}, got {value!r}")


_FIELDS = {f.name: f for f in fields(Settings)}
_INTS = {"concurrency", "drjit_threads", "torch_threads", "frames_per_task", "farm_slots",
         "max_attempts", "failure_budget", "store_retries", "visibility_timeout", "restore_interval",
         "scene_cache", "transport_cache_mb", "heal_after", "heal_interval", "worker_beat"}
_OPTIONAL = {"result_backend", "database_url", "drjit_threads", "frames_per_task", "dashboard_token",
             "s3_endpoint_url", "s3_region", "s3_access_key_id", "s3_secret_access_key"}
# The usual AWS variables, read where no UNDREAM_S3_* variable sets the setting (first one set wins).
AWS_ENV = {"s3_endpoint_url": ("AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL"),
           "s3_region": ("AWS_REGION", "AWS_DEFAULT_REGION"),
           "s3_access_key_id": ("AWS_ACCESS_KEY_ID",), "s3_secret_access_key": ("AWS_SECRET_ACCESS_KEY",)}


def _coerce(source: str, name: str, value: Any) -> Any:
    """A value from a file or the environment as the field's type; errors name ``source``."""
    if value is None or value == "":
        return None if name in _OPTIONAL else _FIELDS[name].default
    if name in _INTS:
        if isinstance(value, (bool, float)):
            return _bad(source, value, "an integer")
        try:
            return int(str(value).strip())
        except ValueError:
            return _bad(source, value, "an integer")
    if name == "benign_cache":
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text not in _TRUE + _FALSE:
            return _bad(source, value, "true or false (1/0, yes/no, on/off)")
        return text in _TRUE
    if name == "connect_timeout":
        try:
            return float(value)
        except (TypeError, ValueError):
            return _bad(source, value, "a number of seconds")
    return str(value)


def _bad(source: str, value: Any, what: str) -> Any:
    raise SettingsError(f"{source}: must be {what}, got {value!r}")


def _from_file(path: Path) -> dict[str, Any]:
    data = read_yaml(path)
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise SettingsError(f"{path}: must be a mapping of settings, got {type(data).__name__}")
    unknown = sorted(set(map(str, data)) - set(_FIELDS))
    if unknown:
        raise SettingsError(f"{path}: {unknown[0]}: unknown setting; valid settings are "
                            f"{', '.join(_FIELDS)}")
    return {k: _coerce(f"{path}: {k}", k, v) for k, v in data.items()}


def settings_file(file: str | Path | None = None, env: Mapping[str, str] | None = None) -> str | Path | None:
    """The settings file :func:`load_settings` reads: ``file``, else ``$UNDREAM_SETTINGS`` of ``env``
    (default ``os.environ``); None when neither names one."""
    env = os.environ if env is None else env
    return file or env.get(SETTINGS_ENV) or None


def load_settings(file: str | Path | None = None, env: Mapping[str, str] | None = None,
                  **overrides: Any) -> Settings:
    """Defaults, then ``file`` (or ``$UNDREAM_SETTINGS``), then ``UNDREAM_*`` variables of
    ``env`` (default ``os.environ``), then the ``overrides`` that are not None (flags)."""
    env = os.environ if env is None else env
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for name, variables in AWS_ENV.items():
        var = next((v for v in variables if env.get(v)), None)
        if var is not None:
            values[name] = env[var]
            sources[name] = var
    path = settings_file(file, env)
    if path:
        values.update(_from_file(Path(path)))
        sources.update({k: f"{path}: {k}" for k in values})
    for name in _FIELDS:
        var = ENV_PREFIX + name.upper()
        if var in env:
            values[name] = _coerce(var, name, env[var])
            sources[name] = var
    unknown = sorted(set(overrides) - set(_FIELDS))
    if unknown:
        raise SettingsError(f"{unknown[0]}: unknown setting; valid settings are {', '.join(_FIELDS)}")
    for name, value in overrides.items():
        if value is not None:
            values[name] = value
            sources[name] = f"--{name.replace('_', '-')}"
    try:
        return Settings(**values)
    except SettingsError as err:
        name, _, rest = str(err).partition(": ")
        raise SettingsError(f"{sources[name]}: {rest}" if name in sources else str(err)) from None


# --- per-process settings of every command and worker process --------------------------------------

MI_VARIANT_ENV = "UNDREAM_MI_VARIANT"
FROZEN_ENV = "UNDREAM_FROZEN"
MEMORY_LIMIT_ENV = "UNDREAM_MEMORY_LIMIT"  # bytes, or with a K/M/G/T suffix
BLENDER_PYTHON_ENV = "UNDREAM_BLENDER_PYTHON"
BLENDER_THREADS_ENV = "UNDREAM_BLENDER_THREADS"
UNREAL_SPOOL_ENV = "UNDREAM_UNREAL_SPOOL"
UNREAL_TIMEOUT_ENV = "UNDREAM_UNREAL_TIMEOUT"
DRJIT_THREADS_ENV = "UNDREAM_DRJIT_THREADS"  # also the farm's drjit_threads (Settings)
HF_OFFLINE_ENVS = ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")
DEFAULT_LIBCUDA = "libcuda.so.1"
_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")
BENIGN_CACHE_ENV = "UNDREAM_BENIGN_CACHE"  # also the farm's benign_cache (Settings)


@dataclass(frozen=True)
class LocalSettings:
    """How this process renders and loads (see the module docstring for the variables).

    Built at the edge by :func:`load_local`; the library gets it (or single
    fields of it) as parameters. The defaults are the library's own defaults.
    """

    mi_variant: str | None = None  # None: the first of cuda_ad_rgb, llvm_ad_rgb that works
    frozen: bool = True  # the simulator's renders as Dr.Jit frozen functions
    memory_limit: int | None = None  # bytes a render may use; None: the system's MemAvailable
    blender_python: str | None = None  # None: <repo>/.venv-blender/bin/python
    blender_threads: int | None = None  # Cycles' threads; None: the process's Dr.Jit threads
    drjit_threads: int | None = None  # Dr.Jit's pool in this process; None: Dr.Jit's default (the cores)
    unreal_spool: str | None = None  # the Unreal spool folder; None: none (sim: unreal refuses)
    unreal_timeout_s: float | None = None  # None: undream.sim.unreal.DEFAULT_TIMEOUT_S
    hf_offline: bool = False  # never ask the Hugging Face hub
    cache_home: str = ""  # "" → ~/.cache
    libcuda_path: str = DEFAULT_LIBCUDA  # the CUDA driver library Dr.Jit loads
    cuda_visible_devices: str | None = None  # as set, for messages
    benign_cache: bool = True  # `undream run` keeps benign evaluations in <cache_home>/undream/benign
    # What child processes (Blender's interpreter) get as their environment; None: only what
    # undream sets for them. Not compared or shown: it may hold secrets.
    child_env: Mapping[str, str] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.cache_home:
            object.__setattr__(self, "cache_home", str(Path.home() / ".cache"))
        if self.blender_threads is not None:
            _check_int("blender_threads", self.blender_threads, 0)
        if self.drjit_threads is not None:
            _check_int("drjit_threads", self.drjit_threads, 1)

    @property
    def undream_cache(self) -> str:
        """undream's own cache folder, ``<cache_home>/undream``: fetched weights and assets
        (``assets/NAME``), the benign evaluations, converted .blend files."""
        return str(Path(self.cache_home) / "undream")


def parse_bytes(text: str, source: str = MEMORY_LIMIT_ENV) -> int:
    """``"8G"``, ``"512M"`` or ``"1000000"`` as bytes (powers of 1024); SpecError naming ``source``."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KMGT]?)i?B?\s*", str(text), re.IGNORECASE)
    if not match:
        raise SettingsError(f"{source}: {text!r} is not a size; give bytes, or a number with K, M, G or T")
    power = " KMGT".index(match.group(2).upper() or " ")
    return int(float(match.group(1)) * 1024**power)


def load_local(env: Mapping[str, str] | None = None) -> LocalSettings:
    """The :class:`LocalSettings` of ``env`` (default ``os.environ``); SettingsError naming the variable."""
    env = os.environ if env is None else env
    threads = env.get(BLENDER_THREADS_ENV, "").strip()
    if threads and not (threads.isdigit()):
        raise SettingsError(f"{BLENDER_THREADS_ENV}: must be a whole number of threads (0: all cores), "
                            f"got {threads!r}")
    drjit = env.get(DRJIT_THREADS_ENV, "").strip()
    if drjit and not (drjit.isdigit() and int(drjit) >= 1):
        raise SettingsError(f"{DRJIT_THREADS_ENV}: must be a whole number of threads >= 1, got {drjit!r}")
    timeout = env.get(UNREAL_TIMEOUT_ENV, "").strip()
    try:
        timeout_s = float(timeout) if timeout else None
    except ValueError:
        raise SettingsError(f"{UNREAL_TIMEOUT_ENV}: must be a number of seconds > 0, got {timeout!r}") from None
    if timeout_s is not None and not timeout_s > 0:
        raise SettingsError(f"{UNREAL_TIMEOUT_ENV}: must be a number of seconds > 0, got {timeout!r}")
    limit = env.get(MEMORY_LIMIT_ENV, "")
    return LocalSettings(
        mi_variant=env.get(MI_VARIANT_ENV) or None,
        frozen=env.get(FROZEN_ENV, "1") != "0",
        memory_limit=parse_bytes(limit) if limit else None,
        blender_python=env.get(BLENDER_PYTHON_ENV) or None,
        blender_threads=int(threads) if threads else None,
        drjit_threads=int(drjit) if drjit else None,
        unreal_spool=env.get(UNREAL_SPOOL_ENV) or None,
        unreal_timeout_s=timeout_s,
        hf_offline=any(env.get(v, "").strip().lower() in _TRUE for v in HF_OFFLINE_ENVS),
        cache_home=str(cache_home(env)),
        libcuda_path=env.get("DRJIT_LIBCUDA_PATH") or DEFAULT_LIBCUDA,
        cuda_visible_devices=env.get("CUDA_VISIBLE_DEVICES"),
        benign_cache=_coerce(BENIGN_CACHE_ENV, "benign_cache", env.get(BENIGN_CACHE_ENV, "")),
        child_env=dict(env),
    )
