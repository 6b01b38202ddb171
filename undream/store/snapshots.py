"""Read-only snapshots of store rows, and the JSON text those rows hold.

Callers never get live ORM objects: each read returns frozen dataclasses built
inside the transaction, safe to keep, pass between threads or serialize.
"""
from __future__ import annotations

import datetime as dt
import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

from undream.errors import SpecError, StoreError
from undream.spec.run import RunConfig
from undream.store.models import IterationRecord, Run, Sweep


def finite_or_none(value: float | None) -> float | None:
    """``float(value)`` when finite, else None (what the database stores)."""
    if value is None:
        return None
    number = float(value)
    return number if math.isfinite(number) else None


def _strict(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(v) for v in value]
    if isinstance(value, np.generic):
        return _strict(value.item())
    return value


def dumps(field: str, data: Any) -> str:
    """``data`` as strict JSON text; non-finite floats become null."""
    try:
        return json.dumps(_strict(data), allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise StoreError(f"{field}: not JSON-able ({exc}); give dicts, lists, strings, "
                         "numbers, booleans or None") from None


def loads(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def loads_many(texts: list[str | None]) -> list[Any]:
    """:func:`loads` of each text, decoded as one JSON array (one call instead of one per text:
    thousands of small documents decode several times faster). Every stored text is strict JSON."""
    return json.loads("[" + ",".join("null" if t is None else t for t in texts) + "]")


def _utc(stamp: dt.datetime | None) -> dt.datetime | None:
    """SQLite returns naive datetimes; every stored time is UTC."""
    if stamp is None or stamp.tzinfo is not None:
        return stamp
    return stamp.replace(tzinfo=dt.timezone.utc)


@dataclass(frozen=True)
class RunSnapshot:
    """A run as stored. ``iteration``: completed steps (texture ``iteration`` is the latest)."""

    id: str
    name: str
    config: dict[str, Any]
    status: str
    iteration: int
    n_frames: int
    seed: int
    created: dt.datetime
    updated: dt.datetime
    error: str | None
    attack_state_ref: str | None
    results: dict[str, Any] | None
    scene_ref: str | None = None
    out_dir: str | None = None
    sweep_id: str | None = None
    farm: dict[str, Any] = field(default_factory=dict)
    failures: int = 0
    owner: str | None = None  # host:pid of the process holding the run's lease (``undream run``)
    heartbeat: dt.datetime | None = None  # that process's last heartbeat (UTC)

    @cached_property
    def run_config(self) -> RunConfig:
        """The run's config, typed, with every default filled in (the attack's steps and seed
        included): the one way to read what the run was asked to do. A run stored before
        ``holdout`` existed held nothing out, and reads so."""
        try:
            return RunConfig.from_json({"holdout": "none", **self.config})
        except SpecError as err:
            raise StoreError(f"run {self.id}: its stored config is not a run config this version reads "
                             f"({err})") from None

    @classmethod
    def of(cls, row: Run) -> "RunSnapshot":
        return cls(id=row.id, name=row.name, config=loads(row.config_json), status=row.status,
                   iteration=row.iteration, n_frames=row.n_frames, seed=row.seed,
                   created=_utc(row.created), updated=_utc(row.updated),  # type: ignore[arg-type]
                   error=row.error, attack_state_ref=row.attack_state_ref,
                   results=loads(row.results_json), scene_ref=row.scene_ref, out_dir=row.out_dir,
                   sweep_id=row.sweep_id, farm=loads(row.farm_json) or {}, failures=row.failures or 0,
                   owner=row.owner, heartbeat=_utc(row.heartbeat))


@dataclass(frozen=True)
class SweepSnapshot:
    """A sweep: its name and spec (the base config and the grid)."""

    id: str
    name: str
    spec: dict[str, Any]
    created: dt.datetime

    @classmethod
    def of(cls, row: Sweep) -> "SweepSnapshot":
        return cls(id=row.id, name=row.name, spec=loads(row.spec_json),
                   created=_utc(row.created))  # type: ignore[arg-type]


class JobLine(NamedTuple):
    """What a display of many jobs needs of each (:meth:`Store.job_lines`): a light
    :class:`JobSnapshot` with the same attribute names; ``timings`` in seconds, ``result`` the
    job's JSON (an attack job's prediction, an evaluation's prediction and loss) or None."""

    k: int
    frame: int
    status: str
    attempts: int
    worker: str | None
    error: str | None
    timings: dict[str, Any]
    result: dict[str, Any] | None


@dataclass(frozen=True)
class JobSnapshot:
    """One frame job. ``loss`` is None until it succeeds, or when not finite.

    ``phase``: ``attack`` (``grad_ref``, ``loss``; ``result`` the victim's prediction on the
    frame it rendered, None for jobs stored before it was kept), ``pre`` or ``adversarial``
    (evaluation: ``result`` holds the prediction and loss, ``image_ref`` the frame).
    """

    run_id: str
    k: int
    frame: int
    status: str
    attempts: int
    loss: float | None
    finite: bool
    grad_ref: str | None
    timings: dict[str, Any]
    error: str | None
    started: dt.datetime | None
    finished: dt.datetime | None
    phase: str = "attack"
    result: dict[str, Any] | None = None
    image_ref: str | None = None
    worker: str | None = None

    @classmethod
    def many(cls, rows: list[Any]) -> list["JobSnapshot"]:
        """:meth:`of` each row of the frame-job table, their JSON decoded together."""
        timings = loads_many([r.timings_json for r in rows])
        results = loads_many([r.result_json for r in rows])
        return [cls(run_id=r.run_id, k=r.k, frame=r.frame, status=r.status, attempts=r.attempts,
                    loss=r.loss, finite=bool(r.finite), grad_ref=r.grad_ref, timings=t or {},
                    error=r.error, started=_utc(r.started), finished=_utc(r.finished), phase=r.phase,
                    result=res, image_ref=r.image_ref, worker=r.worker)
                for r, t, res in zip(rows, timings, results)]

    @classmethod
    def of(cls, row: Any) -> "JobSnapshot":
        """From a :class:`FrameJob` or a row of its table (the same attribute names)."""
        return cls(run_id=row.run_id, k=row.k, frame=row.frame, status=row.status,
                   attempts=row.attempts, loss=row.loss, finite=bool(row.finite),
                   grad_ref=row.grad_ref, timings=loads(row.timings_json) or {},
                   error=row.error, started=_utc(row.started), finished=_utc(row.finished),
                   phase=row.phase, result=loads(row.result_json), image_ref=row.image_ref,
                   worker=row.worker)


@dataclass(frozen=True)
class IterationSnapshot:
    """Metrics of step ``k`` → ``k+1``; non-finite values read back as None."""

    run_id: str
    k: int
    loss_mean: float | None
    n_ok: int
    n_bad: int
    dropped_frames: list[int]
    grad_norm: float | None
    step_seconds: float | None
    per_frame: Any
    created: dt.datetime
    terms: dict[str, float | None] = field(default_factory=dict)  # the objective's named terms

    @classmethod
    def of(cls, row: IterationRecord) -> "IterationSnapshot":
        return cls(run_id=row.run_id, k=row.k, loss_mean=row.loss_mean, n_ok=row.n_ok,
                   n_bad=row.n_bad, dropped_frames=loads(row.dropped_json) or [],
                   grad_norm=row.grad_norm, step_seconds=row.step_seconds,
                   per_frame=loads(row.per_frame_json),
                   created=_utc(row.created), terms=loads(row.terms_json) or {})  # type: ignore[arg-type]


class FrameGrad(NamedTuple):
    """One frame's contribution at iteration ``k``; ``grad`` is None unless the job succeeded."""

    frame: int
    grad: np.ndarray | None
    loss: float | None
    finite: bool
