"""A run to record (:class:`NewRun`) and the ``runs`` row it becomes, checked before anything is written."""
from __future__ import annotations

import datetime as dt
import uuid
from dataclasses import dataclass, field
from typing import Any, Mapping

from undream.errors import StoreError
from undream.store.checks import MAX_SEED, integer, mapping
from undream.store.snapshots import dumps


def _new_id() -> str:
    return str(uuid.uuid4())


@dataclass(frozen=True)
class NewRun:
    """A queued run at iteration 0, before it is recorded (:meth:`undream.store.Store.create_runs`).

    ``config``: the run config as plain JSON data; ``scene_ref``: blob key of the
    packed scene; ``out_dir``: where the run's outputs go; ``farm``: its
    scheduling options (plain JSON). ``id`` is chosen here (a UUID string), so
    the caller knows every run's id before the transaction that records them.
    """

    name: str
    config: Mapping[str, Any]
    n_frames: int
    seed: int
    scene_ref: str | None = None
    out_dir: str | None = None
    farm: Mapping[str, Any] | None = None
    id: str = field(default_factory=_new_id)


def check_name(name: Any) -> str:
    if not isinstance(name, str) or not name.strip() or len(name) > 200:
        raise StoreError(f"name: must be a non-empty string of at most 200 characters, got {name!r}")
    return name


def run_row(run: NewRun, sweep_id: str | None, created: dt.datetime) -> dict[str, Any]:
    """The ``runs`` row of ``run`` (queued, iteration 0, in sweep ``sweep_id``), every field checked."""
    if not isinstance(run, NewRun):
        raise StoreError(f"runs: each must be a NewRun, got {type(run).__name__}")
    if not isinstance(run.id, str) or not 1 <= len(run.id) <= 36:
        raise StoreError(f"id: must be a string of 1 to 36 characters, got {run.id!r}")
    mapping("config", run.config)
    return {"id": run.id, "name": check_name(run.name), "status": "queued", "iteration": 0,
            "config_json": dumps("config", dict(run.config)),
            "n_frames": integer("n_frames", run.n_frames, 1), "seed": integer("seed", run.seed, 0, MAX_SEED),
            "scene_ref": run.scene_ref, "out_dir": None if run.out_dir is None else str(run.out_dir),
            "sweep_id": sweep_id, "farm_json": dumps("farm", dict(run.farm or {})),
            "created": created, "updated": created}
