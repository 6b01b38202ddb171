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
    from undream.spec import Sequence
    from undream.spec.run import RunConfig
    from undream.store import RunSnapshot


@dataclass(frozen=True)
class FarmOptions:
    """How a run is scheduled, fixed when it is submitted (stored with the run)."""

    frames_per_task: int = 1
    max_attempts: int = 3
    failure_budget: int = 2
    # A multi-condition run's attacked frame positions (its split needs the sequence's conditions,
    # which a reader of the run does not load); None: split_frames of the run's holdout.
    attacked: tuple[int, ...] | None = None
    # Read the benign evaluation from the blob store when a run with the same key computed it
    # (scheduler.benign), and keep it there when not.
    benign_cache: bool = True

    @classmethod
    def of(cls, run: "RunSnapshot") -> "FarmOptions":
        return cls(**{k: v for k, v in run.farm.items() if k in cls.__dataclass_fields__})

    @classmethod
    def from_settings(cls, settings: "Settings", config: "RunConfig", sequence: "Sequence") -> "FarmOptions":
        """The settings' options for a run of ``config`` over ``sequence``: tasks sized for the
        frames an iteration renders (the attacked ones, or ``frames_per_step`` of them), so each
        iteration's frames spread evenly over the farm's slots."""
        attacked = len(config.split(sequence).attacked)
        per_iteration = min(config.attack.frames_per_step or attacked, attacked)
        return cls(settings.frames_per_task_for(per_iteration), settings.max_attempts, settings.failure_budget,
                   attacked_positions(config, sequence), settings.benign_cache)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        if self.attacked is None:
            del d["attacked"]  # a run of one scene: as before multi-condition runs
        else:
            d["attacked"] = list(self.attacked)
        if self.benign_cache:
            del d["benign_cache"]  # on: as runs stored before the cache existed read
        return d


def attacked_positions(config: "RunConfig", sequence: "Sequence") -> tuple[int, ...] | None:
    """What :attr:`FarmOptions.attacked` records for a run of ``config`` over ``sequence``."""
    return tuple(config.split(sequence).attacked) if config.conditions is not None else None


def attacked_frames(run: "RunSnapshot") -> list[int]:
    """The frame positions the attack may render for its gradient (the held-out ones excluded)."""
    recorded = FarmOptions.of(run).attacked
    if recorded is not None:
        return list(recorded)
    return split_frames(run.run_config.holdout, run.n_frames)[0]
