"""How a run is scheduled on the farm, fixed when it is submitted and stored with the run.

Apart from :mod:`scheduler.stages` (which re-exports it) so that a reader of runs
(:mod:`workers.health`, ``undream status``) gets it without loading the stages.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

from undream.spec.run import split_frames

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.spec.run import RunConfig
    from undream.store import RunSnapshot


@dataclass(frozen=True)
class FarmOptions:
    """How a run is scheduled, fixed when it is submitted (stored with the run)."""

    frames_per_task: int = 1
    max_attempts: int = 3
    failure_budget: int = 2

    @classmethod
    def of(cls, run: "RunSnapshot") -> "FarmOptions":
        return cls(**{k: v for k, v in run.farm.items() if k in cls.__dataclass_fields__})

    @classmethod
    def from_settings(cls, settings: "Settings", config: "RunConfig", n_frames: int) -> "FarmOptions":
        """The settings' options for a run of ``config`` over ``n_frames`` frames: tasks sized for the
        frames an iteration renders (the attacked ones, or ``frames_per_step`` of them), so each
        iteration's frames spread evenly over the farm's slots."""
        attacked = len(split_frames(config.holdout, n_frames)[0])
        per_iteration = min(config.attack.frames_per_step or attacked, attacked)
        return cls(settings.frames_per_task_for(per_iteration), settings.max_attempts, settings.failure_budget)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)
