"""Which texels some frame sees: the scene's visibility, never a guess from the texture.

A texel counts as seen when a gradient pass over *every* frame (attacked and
held-out), seeded with a white image gradient at :data:`MIN_SPP` samples per
pixel (or the run's ``grad_spp`` when higher) and the run's seed, reaches it:
:func:`undream.engine.algorithm.visibility`, the function a run with
``random_start`` calls when it starts. Without the scene, that run's stored
mask (computed at ``grad_spp``) is used. "Unchanged from T0" is not used: it
also holds for seen texels the attack left alone (clipped, zero gradient,
or seen only by held-out frames).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from undream.render.scene_cache import SceneCache
from undream.report.data import Seen
from undream.spec.io import load_sequence

if TYPE_CHECKING:
    from undream.render.scene_cache import SceneCache
    from undream.store import RunSnapshot, Store

STORED = ("from the scene's visibility, computed when the run started (random start) at the run's "
          "grad_spp: the scene itself is no longer at hand")
COMPUTED = ("from the scene's visibility: a gradient pass over every frame, attacked and held-out, "
            "seeded with a white image gradient at {spp} samples per pixel and the run's seed ({seed}); "
            "a texel no frame's gradient reaches is unseen (undream.engine.algorithm.visibility)")
MIN_SPP = 32  # samples per pixel of the visibility pass at least: at 2 spp it misses texels the attack changed


def _scene_from_metadata(folder: Path) -> Path | None:
    """The scene directory a run's ``metadata.json`` in ``folder`` names, when it still exists."""
    try:
        meta = json.loads((folder / "metadata.json").read_text())
    except (OSError, ValueError):
        return None
    scene = Path(str(meta.get("scene_dir") or "")) if isinstance(meta, dict) else None
    return scene if scene is not None and (scene / "sequence.json").is_file() else None


class SeenFinder:
    """Finds runs' seen texels; scenes unpacked under ``work_dir`` and loaded once (close when done)."""

    def __init__(self, store: "Store", work_dir: Path) -> None:
        self.store = store
        self.work_dir = Path(work_dir)
        self._scenes: dict[Path, "SceneCache"] = {}
        self._masks: dict[tuple[Path, int, int], np.ndarray] = {}

    def close(self) -> None:
        for cache in self._scenes.values():
            cache.close()
        self._scenes.clear()

    def scene_dir(self, run: "RunSnapshot", folder: Path | None) -> Path | None:
        """The run's scene: its blob in the store (farm runs), else the one its output folder names."""
        if run.scene_ref:
            from scheduler.scenes import unpack_scene

            return unpack_scene(self.store.blobs, run.scene_ref, self.work_dir)
        for where in (folder, Path(run.out_dir) if run.out_dir else None):
            found = _scene_from_metadata(where) if where is not None else None
            if found is not None:
                return found
        return None

    def __call__(self, run: "RunSnapshot", texture0: np.ndarray, folder: Path | None = None) -> Seen:
        """The texels of ``texture0`` (H×W×3) that some frame of ``run`` sees, and how that was found."""
        scene = self.scene_dir(run, folder)
        if scene is None:
            state0 = self.store.attack_state(run.id, 0) or {}
            visible = state0.get("visible")
            if isinstance(visible, np.ndarray) and visible.shape == texture0.shape[:2] and visible.any():
                return Seen(visible.astype(bool), STORED)
            return Seen(None, "unknown: the run's scene directory is no longer where its metadata.json "
                              "says, and the store holds no copy of it")
        spp, seed = max(MIN_SPP, run.run_config.grad_spp), run.run_config.seed
        key = (scene.resolve(), spp, seed)
        if key not in self._masks:
            self._masks[key] = self._visibility(scene, spp, seed, texture0)
        return Seen(self._masks[key], COMPUTED.format(spp=spp, seed=seed))

    def _visibility(self, scene: Path, spp: int, seed: int, texture0: np.ndarray) -> np.ndarray:
        from undream.engine.algorithm import visibility  # torch: only when a report needs a pass

        if scene not in self._scenes:
            self._scenes[scene] = SceneCache(scene)
        frames = load_sequence(scene / "sequence.json").frames  # no victim or simulator is loaded
        return visibility(self._scenes[scene], frames, np.ascontiguousarray(texture0, dtype=np.float32), spp, seed)
