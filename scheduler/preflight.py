"""Before ``undream run`` writes or deletes anything: validate the whole run, and the output folder rule.

:func:`preflight` checks what can be checked without rendering, in order of
cost: the attack block, the store URL, the scene source (a scene directory's
``sequence.json`` or a spec file, parsed), the victim (loaded) and its labels.
:func:`check_output_folder` then says whether ``--out`` may be used:
``--force`` only ever replaces a folder that ``undream run`` created
(recognised by its ``metadata.json``, written when the run starts and again
with the results), and never one that holds the run's own scene or spec.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from undream.errors import SpecError, already_exists
from undream.spec.run import RunConfig

if TYPE_CHECKING:
    from undream.victims import Victim

METADATA = "metadata.json"
MARKER = "undream_output"  # key of the metadata.json written when a run starts


def scene_source(config: RunConfig, base_dir: Path) -> Path:
    """The run's scene as the user named it: a scene directory or a spec file (absolute)."""
    src = Path(config.scene)
    return (src if src.is_absolute() else Path(base_dir) / src).resolve()


def preflight(config: RunConfig, base_dir: Path) -> "Victim":
    """Validate everything a run needs that rendering does not; returns the loaded victim."""
    from undream.engine.context import attack_of, class_ids, task_of
    from undream.victims import load_victim

    attack_of(config)
    if config.store:
        from undream.store.db import make_engine

        make_engine(config.store).dispose()
    seq = _sequence(scene_source(config, base_dir))
    check_frames(config, len(seq.frames))
    victim = load_victim(config.victim, device=config.device, task=task_of(config))
    class_ids(config, seq, victim)
    return victim


def check_frames(config: RunConfig, n_frames: int) -> None:
    """The attack's ``frames_per_step`` fits the sequence."""
    per_step = config.attack.get("frames_per_step")
    if isinstance(per_step, int) and per_step > n_frames:
        raise SpecError(f"attack.frames_per_step: {per_step} is more than the sequence's {n_frames} frames")


def _sequence(src: Path) -> Any:
    from undream.scene.sources import sequence_from_file
    from undream.spec import load_sequence

    if (src / "sequence.json").is_file():
        return load_sequence(src / "sequence.json")
    if not src.is_file():
        raise SpecError(f"scene: {src} is neither a scene directory nor a spec file")
    return sequence_from_file(src)


def is_run_output(folder: Path) -> bool:
    """Whether ``folder`` is an output folder of ``undream run`` (its ``metadata.json`` says so)."""
    try:
        meta = json.loads((Path(folder) / METADATA).read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and (MARKER in meta or "run_id" in meta)


def check_output_folder(out: Path, scene_src: Path, force: bool) -> None:
    """Refuse an ``--out`` the run must not use (see the module docstring); nothing is touched."""
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise SpecError(f"--out {out}: exists and is not a folder")
    existing = next(p for p in (out, *out.parents) if p.exists())
    if not existing.is_dir():
        raise SpecError(f"--out {out}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise SpecError(f"--out {out}: no permission to write in {existing}")
    if out == scene_src or out in scene_src.parents:
        raise SpecError(f"--out {out}: holds the run's scene {scene_src}; choose another output folder")
    if out.exists() and any(out.iterdir()):
        if not force:
            raise already_exists(out)
        if not is_run_output(out):
            raise SpecError(f"--out {out}: --force only replaces a folder that `undream run` wrote "
                            f"(one with its {METADATA}); this one has none, so it is left as it is")


def mark_output(out: Path, config: RunConfig) -> None:
    """Write the starting ``metadata.json`` that makes ``out`` a run's output folder."""
    (Path(out) / METADATA).write_text(json.dumps({MARKER: "run", "status": "started",
                                                  "config": config.to_json()}, indent=1) + "\n")
