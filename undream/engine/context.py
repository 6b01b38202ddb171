"""Everything a process needs to run frame jobs of one run, loaded once and cached."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from undream.attacks import make_attack
from undream.engine.crops import CropFrames
from undream.engine.gradient import GradientPath
from undream.errors import SpecError, VictimError
from undream.printing.gamut import Gamut, load_gamut
from undream.printing.profiles import resolve_gamut
from undream.render.scene_cache import SceneCache
from undream.scenedir.verify import mask_box, read_mask
from undream.settings import LocalSettings
from undream.sim import SimulatorBackend, backend_options, make_backend
from undream.spec import Sequence, load_sequence
from undream.spec.run import TASK_LOSSES, RunConfig

if TYPE_CHECKING:
    from undream.attacks.base import Attack
    from undream.victims import Target, Victim


@dataclass
class RunContext:
    """A run's scene, simulator, victim, per-frame targets and attack (one per process).

    Frames are addressed by *position* (0 … n−1 in ``sequence.frames``); a
    frame's *index* (``Frame.index``, in its file names) may differ.
    """

    config: RunConfig
    scene_dir: Path
    sequence: Sequence
    scenes: SceneCache  # Mitsuba scenes: the gradient renders (and the simulator's, when it is Mitsuba)
    sim: SimulatorBackend  # renders the frames the victim sees
    victim: "Victim"
    targets: list["Target"]  # one per frame position
    attack: "Attack"
    gradients: GradientPath  # each frame's texture gradient: captured transport or prb
    crops: CropFrames = None  # type: ignore[assignment]  # what an iteration renders of each frame
    gamut: Gamut | None = None  # the printer's gamut each step's texture is projected into (config.gamut)

    def __post_init__(self) -> None:
        if self.crops is None:
            self.crops = CropFrames(self)

    @property
    def frame_indices(self) -> list[int]:
        return [f.index for f in self.sequence.frames]


# Built-ins that are a part of an object whose class they take by default (the plate of a stop sign).
PART_OF = {"stop_sign_plate": "stop_sign"}


def class_id(victim: Any, name: str, field: str) -> int:
    """The victim's class id of ``name`` (case-insensitive, ``_`` read as a space: the built-in
    ``stop_sign`` is COCO's ``stop sign``); errors name the field and the classes."""
    labels = [_class_key(x) for x in victim.labels]
    if _class_key(name) not in labels:
        shown = ", ".join(victim.labels[:20]) + (" ..." if len(victim.labels) > 20 else "")
        raise VictimError(f"{field}: {name!r} is not one of {victim.name}'s classes ({shown})")
    return labels.index(_class_key(name))


def _class_key(name: Any) -> str:
    return " ".join(str(name).lower().replace("_", " ").split())


def class_ids(config: RunConfig, seq: Sequence, victim: Any) -> tuple[int, int | None]:
    """The victim's class ids of the object (``label``, default: the built-in asset's name, or for a
    part the whole's, :data:`PART_OF`) and of
    ``target_label``; errors name the field, and a target equal to the object's own class is one."""
    own = seq.asset.builtin
    label = class_id(victim, config.label or PART_OF.get(own or "", own) or seq.asset.name, "label")
    if not config.target_label:
        return label, None
    target = class_id(victim, config.target_label, "target_label")
    if target == label:
        raise SpecError(f"target_label: {config.target_label!r} is the object's own class (label); "
                        "a targeted attack needs another class")
    return label, target


def task_of(config: RunConfig) -> str:
    """The victim's task that the run's loss belongs to (``classification`` or ``detection``)."""
    return next(t for t, kinds in TASK_LOSSES.items() if config.loss in kinds)


def refresh_iterations(config: RunConfig, seq: Sequence) -> int:
    """Iterations between two captures of a frame's transport: ``transport_refresh`` passes over the
    attacked frames. A run that renders every attacked frame per iteration passes once per iteration;
    a minibatched one (``attack.frames_per_step``) once per ⌈attacked / frames_per_step⌉ iterations, so
    each frame is captured about every ``transport_refresh`` uses, not at nearly every use."""
    per_step = config.attack.frames_per_step
    if per_step is None:
        return config.transport_refresh
    attacked = len(config.split(seq).attacked)
    return config.transport_refresh * max(1, -(-attacked // per_step))


def build_context(config: RunConfig, scene_dir: Path, *, victim: "Victim | None" = None,
                  scenes: SceneCache | None = None, local: LocalSettings = LocalSettings()) -> RunContext:
    """Load the sequence, scenes, victim and attack of a run.

    ``victim`` and ``scenes``: already loaded ones to share (a farm worker
    serving several runs of one scene and victim loads them once); loaded here
    when None. The victim is put behind the run's ``defence`` here
    (:func:`undream.victims.defended.defend`), so every path that builds a context judges the
    defended victim. Everything else is the run's own. ``local``: this process's
    settings, read at the edge (frozen renders, the simulator's options, the hub).
    """
    import torch

    from undream.victims import Target, load_victim
    from undream.victims.defended import defend

    # Small victims on CPU: one thread avoids OpenMP spinning against Dr.Jit's
    # render threads (measured: ~0.03 s per loss+grad+predict call with 1 thread,
    # 0.1–2.3 s with 2 threads while rendering on the same 2 cores).
    torch.set_num_threads(config.torch_threads)
    seq = load_sequence(scene_dir / "sequence.json")
    task = task_of(config)
    if victim is None:
        victim = load_victim(config.victim, device=config.device, task=task, offline=local.hf_offline,
                             cache_home=local.cache_home)
    victim = defend(victim, config.defence, config.seed)  # the evaluation judges it; attacks: attacker_view
    label, target = class_ids(config, seq, victim)
    targets = [Target(label=label, target_label=target,
                      box=mask_box(read_mask(scene_dir, f.index)) if task == "detection" else None)
               for f in seq.frames]
    attack = make_attack(config.attack)
    if scenes is None:
        scenes = SceneCache(scene_dir, frozen=local.frozen)
    sim = make_backend(config.sim, scene_dir, **({"scenes": scenes} if config.sim == "mitsuba" else {}),
                       **backend_options(config.sim, local))
    gradients = GradientPath(scenes, config.gradient, refresh_iterations(config, seq), config.seed)
    return RunContext(config, scene_dir, seq, scenes, sim, victim, targets, attack, gradients,
                      gamut=run_gamut(config, local))


def run_gamut(config: RunConfig, local: LocalSettings = LocalSettings()) -> Gamut | None:
    """The printer's gamut of ``config.gamut`` (None for ``none``; ``default``: the profile setup fetched
    into ``local``'s cache), built once per process (:func:`undream.printing.gamut.load_gamut`)."""
    profile = resolve_gamut(config.gamut, local.undream_cache)
    return None if profile is None else load_gamut(profile)
