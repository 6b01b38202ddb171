"""Submitting runs: validate everything first, then record the runs, then dispatch them.

Validation builds each run's context exactly as a worker will (the scene
directory, the sequence, the victim and its classes, the attack), so a run
that passes cannot fail a worker for a bad config. Only then is the scene
packed into the blob store, the run recorded and its start dispatched; a run
recorded but not dispatched (the broker vanished in between) starts with
``undream resume``. A sweep and all its runs are recorded in one transaction
(none of them if it is interrupted); runs whose start was not sent stay
queued, and ``undream resume SWEEP`` sends every queued run's start again.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from scheduler import stages
from scheduler.local import resolve_scene
from scheduler.preflight import check_frames
from undream.render.budget import run_estimate
from undream.settings import LocalSettings
from undream.spec.io import resolve_against
from undream.spec.run import RunConfig

if TYPE_CHECKING:
    from scheduler.sweep import Sweep
    from undream.settings import Settings
    from undream.store import NewRun, Store

_SHARED = ("name", "attack", "seed", "sim_spp", "grad_spp", "eval_spp", "store", "transport_refresh")


@dataclass(frozen=True)
class Prepared:
    """A validated run: its config, its scene directory and its number of frames."""

    config: RunConfig
    scene_dir: Path
    sequence: Any  # undream.spec.Sequence

    @property
    def n_frames(self) -> int:
        return len(self.sequence.frames)


def _signature(config: RunConfig, scene_dir: Path) -> str:
    """What the context's validity depends on besides the attack (victim, loss, labels, scene)."""
    data = {k: v for k, v in config.to_json().items() if k not in _SHARED}
    return json.dumps({**data, "scene": str(scene_dir)}, sort_keys=True, default=str)


class Validator:
    """Validates run configs, building each distinct (scene, victim, labels) context once."""

    def __init__(self, work_dir: Path, local: LocalSettings = LocalSettings()) -> None:
        self.work_dir = Path(work_dir)
        self.local = local  # this process's settings, read at the edge
        self._scenes: dict[tuple[Path, str | None], Path] = {}  # (scene, conditions) → scene directory
        self._sequences: dict[str, Any] = {}

    def scene(self, config: RunConfig, base_dir: Path) -> Path:
        src = Path(resolve_against(config.scene, base_dir))
        key = (src, None if config.conditions is None else json.dumps(config.conditions.to_json(), sort_keys=True))
        if key not in self._scenes:
            self._scenes[key] = resolve_scene(config, self.work_dir / str(len(self._scenes)), base_dir,
                                              local=self.local)
        return self._scenes[key]

    def __call__(self, config: RunConfig, base_dir: Path) -> Prepared:
        from undream.attacks import make_attack
        from undream.engine.context import build_context

        scene_dir = self.scene(config, base_dir)
        key = _signature(config, scene_dir)
        if key not in self._sequences:
            ctx = build_context(config, scene_dir, local=self.local)
            ctx.scenes.close()
            self._sequences[key] = ctx.sequence
        else:  # same scene and victim: only the attack can differ
            make_attack(config.attack)
        sequence = self._sequences[key]
        check_frames(config, sequence)
        run_estimate(sequence, config, limit=self.local.memory_limit)  # the renders fit in memory; one line naming the field if not
        return Prepared(config, scene_dir, sequence)


def new_runs(store: "Store", runs: Sequence[Prepared], settings: "Settings", out: Path | None = None,
             out_per_run: bool = False) -> list[NewRun]:
    """Pack the scenes into the blob store (content-addressed: packing one again writes nothing new)
    and give the runs to record.

    ``out``: the output folder (a sweep: ``out/<run name>`` when ``out_per_run``);
    None: ``<blobs>/outputs/<name>-<id>``.
    """
    from scheduler.scenes import store_scene

    keys: dict[Path, str] = {}
    new = []
    for p in runs:
        if p.scene_dir not in keys:
            keys[p.scene_dir] = store_scene(store.blobs, p.scene_dir)
        folder = None if out is None else Path(out).resolve() / (p.config.name if out_per_run else "")
        options = stages.FarmOptions.from_settings(settings, p.config, p.sequence)
        new.append(stages.new_run(p.config, p.n_frames, options, scene_ref=keys[p.scene_dir],
                                  out_dir=None if folder is None else str(folder)))
    return new


def record(store: "Store", runs: Sequence[Prepared], settings: "Settings", out: Path | None = None,
           sweep_id: str | None = None, out_per_run: bool = False) -> list[str]:
    """Pack the scenes, then record the runs (queued; in sweep ``sweep_id`` if given) in one
    transaction: all or none; returns their ids. ``out``, ``out_per_run``: see :func:`new_runs`."""
    return store.create_runs(new_runs(store, runs, settings, out, out_per_run), sweep_id)


def record_sweep(store: "Store", sweep: "Sweep", runs: Sequence[Prepared], settings: "Settings",
                 out: Path | None = None) -> tuple[str, list[str]]:
    """Pack the scenes, then record the sweep and its runs (queued; outputs in ``out/<run name>``)
    in one transaction: an error or an interrupt before it commits leaves no sweep and no run.
    Returns the sweep's id and its runs' ids, in the order of ``runs``."""
    new = new_runs(store, runs, settings, out, out_per_run=True)
    return store.create_sweep(sweep.name, sweep.spec, new), [run.id for run in new]


def dispatch_starts(dispatch: Any, run_ids: Sequence[str]) -> None:
    """Send each run's start; one lost on the way leaves its run queued (``undream resume``)."""
    for run_id in run_ids:
        dispatch.start(run_id)
