"""Before ``undream run`` writes or deletes anything: validate the whole run, and the output folder rule.

:func:`preflight` checks what can be checked without rendering, in order of
cost: the attack block, the simulator (``sim: blender`` needs Blender's
Python), the store URL, the scene source (a scene directory's
``sequence.json`` or a spec file, parsed), the victim (loaded) and its labels.
:func:`check_output_folder` then says whether ``--out`` may be used:
``--force`` only ever replaces a folder that ``undream run`` created
(recognised by its ``metadata.json``, written when the run starts and again
with the results), and never one that holds the run's own scene or spec.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from undream.errors import SpecError, StoreError, UndreamError, already_exists
from undream.redact import redact
from undream.spec.io import check_writable_target
from undream.spec.run import RunConfig

if TYPE_CHECKING:
    from undream.render.budget import Estimate
    from undream.spec import Sequence
    from undream.victims import Victim

METADATA = "metadata.json"
MARKER = "undream_output"  # key of the metadata.json written when a run starts


def scene_source(config: RunConfig, base_dir: Path) -> Path:
    """The run's scene as the user named it: a scene directory or a spec file (absolute)."""
    src = Path(config.scene)
    return (src if src.is_absolute() else Path(base_dir) / src).resolve()


@dataclass(frozen=True)
class Checked:
    """What :func:`preflight` found: the loaded victim, the sequence and the run's estimate."""

    victim: "Victim"
    sequence: "Sequence"
    estimate: "Estimate"


def preflight(config: RunConfig, base_dir: Path, source: str | Path | None = None) -> Checked:
    """Validate everything a run needs that rendering does not, cheapest first.

    The attack, the store URL, the scene (a spec file gets every check of
    ``undream init``: meshes with UVs, the texture, its verification renders'
    memory), the frames per step, the renders' memory (:mod:`undream.render.budget`),
    then the victim (loaded) and its labels. ``source``: the run config's
    file, named at the start of every error.
    """
    if source is None:
        return _preflight(config, base_dir)
    try:
        return _preflight(config, base_dir)
    except StoreError:
        raise
    except UndreamError as err:
        raise type(err)(f"{source}: {err}") from None


def _preflight(config: RunConfig, base_dir: Path) -> Checked:
    from undream.engine.context import attack_of, class_ids, task_of
    from undream.render.budget import run_estimate
    from undream.sim import check_simulator
    from undream.victims import load_victim

    attack_of(config)
    check_simulator(config.sim)
    if config.store:
        from undream.store.db import make_engine

        make_engine(config.store).dispose()
    seq = _sequence(scene_source(config, base_dir))
    check_frames(config, len(seq.frames))
    estimate = run_estimate(seq, config)
    victim = load_victim(config.victim, device=config.device, task=task_of(config))
    class_ids(config, seq, victim)
    return Checked(victim, seq, estimate)


def check_frames(config: RunConfig, n_frames: int) -> None:
    """The held-out split fits the sequence, and ``frames_per_step`` the frames left to attack."""
    from undream.spec.run import split_frames

    attacked, held = split_frames(config.holdout, n_frames)
    per_step = config.attack.get("frames_per_step")
    if isinstance(per_step, int) and per_step > len(attacked):
        raise SpecError(f"attack.frames_per_step: {per_step} is more than the {len(attacked)} frames left "
                        f"to attack (the sequence's {n_frames} frames, {len(held)} held out)")


def _sequence(src: Path) -> "Sequence":
    from undream.scenedir.init import check_source
    from undream.scenedir.verify import check_visible
    from undream.spec import load_sequence

    if (src / "sequence.json").is_file():
        seq = load_sequence(src / "sequence.json")
        check_visible(src, [f.index for f in seq.frames])  # a spec file: `undream init` checks it
        return seq
    if not src.is_file():
        raise SpecError(f"scene: {src} is neither a scene directory nor a spec file")
    return check_source(src).sequence  # what `undream init` checks before writing OUT/scene


def is_run_output(folder: Path) -> bool:
    """Whether ``folder`` is an output folder of ``undream run`` (its ``metadata.json`` says so)."""
    try:
        meta = json.loads((Path(folder) / METADATA).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and (MARKER in meta or "run_id" in meta)


def check_output_folder(out: Path, scene_src: Path, force: bool, command: str = "undream run",
                        marker: str = METADATA) -> None:
    """Refuse an ``--out`` the run must not use (see the module docstring); nothing is touched.

    ``command`` and ``marker``: the command whose folders ``--force`` may replace, and the file
    that marks them (``undream run``'s run metadata, unless another command names its own).
    """
    out = Path(out).resolve()
    check_writable_target(out)
    if out == scene_src or out in scene_src.parents:
        raise SpecError(f"--out {out}: holds the run's scene {scene_src}; choose another output folder")
    if out.exists() and any(out.iterdir()):
        if not force:
            raise already_exists(out)
        if not (is_run_output(out) if marker == METADATA else (out / marker).is_file()):
            raise SpecError(f"--out {out}: --force only replaces a folder that `{command}` wrote "
                            f"(one with its {marker}); this one has none, so it is left as it is")


def mark_output(out: Path, config: RunConfig) -> None:
    """Write the starting ``metadata.json`` that makes ``out`` a run's output folder."""
    (Path(out) / METADATA).write_text(json.dumps({MARKER: "run", "status": "started",
                                                  "config": redact(config.to_json())}, indent=1) + "\n")
