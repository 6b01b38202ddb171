"""The benign evaluation, computed once per what decides it and kept in the blob store.

Every run's ``pre`` evaluation renders each frame with the scene's own texture
(8-bit) and asks the victim about it. For the runs of a sweep over seeds,
budgets or attacks that is the same work: the evaluation renders with
:data:`undream.engine.algorithm.EVAL_SEED`, not the run's seed. So the images
and predictions are kept under a key that holds everything that decides them,
and a run whose key is there reads them instead of rendering (the run's own
job rows and frame blobs are written as before, so results, reports and the
dashboard read the same).

The key is the SHA-256 of a JSON document (:func:`benign_key`, kept beside
the entries as ``key.json``): the scene's content (:func:`scene_digest`: its
files but its provenance and verification renders), the benign
texture's digest, the frames, the simulator (name, versions, Mitsuba variant,
frozen renders), ``eval_spp``, the evaluation seed, the victim (name, task,
device, a digest of its weights and settings, torch threads, ``victim_batch``)
and the code (a digest of undream's and the scheduler's source, and the
versions of numpy, torch, Mitsuba, ...). Layout in the blob store::

    benign/<key>/key.json     the key's document
    benign/<key>/0003.npy     frame position 3 rendered with the benign texture (H×W×3 uint8 sRGB)
    benign/<key>/0003.json    its prediction and the batch of positions the victim judged it in

A batch reads the cache only when every one of its frames is there and was
judged in the same batch (the victim's batches decide float rounding), so a
run reads exactly what it would have computed; otherwise it computes the
batch as before and writes it. Two runs that reach the same batch at once
both compute it, and the later write replaces the earlier (writes are whole
and idempotent). Nothing deletes entries: deleting a run leaves them, and
``benign/`` grows by one image and one small JSON document per frame and key.
"""
from __future__ import annotations

import functools
import hashlib
import json
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

import scheduler
import undream
from undream.errors import StoreError
from undream.store import BlobStore
from undream.store.blobs import array_digest
from undream.store.snapshots import dumps
from undream.versions import versions

if TYPE_CHECKING:
    from undream.engine.context import RunContext

PREFIX = "benign"
_VICTIM_DIGESTS: "weakref.WeakKeyDictionary[Any, str]" = weakref.WeakKeyDictionary()


def _hash_files(h: Any, root: Path, pattern: str, skip: tuple[str, ...] = ()) -> None:
    for p in sorted(q for q in root.rglob(pattern) if q.is_file() and "__pycache__" not in q.parts):
        name = p.relative_to(root).as_posix()
        if not any(name == s or name.startswith(s + "/") for s in skip):
            h.update(name.encode() + b"\0")
            h.update(hashlib.sha256(p.read_bytes()).digest())


def scene_digest(scene_dir: Path) -> str:
    """SHA-256 over a scene directory's files (sorted relative paths and their contents) but its
    ``metadata.json`` (when and with what it was made; the versions are in the key) and ``verify/``
    (white-texture renders and masks: no frame render or prediction reads them; the masks make the
    detection targets, which a run judges itself): two runs that initialise the same spec get the
    same digest."""
    h = hashlib.sha256()
    _hash_files(h, Path(scene_dir), "*", skip=("metadata.json", "verify"))
    return h.hexdigest()


@functools.lru_cache(maxsize=16)
def _unpacked_digest(scene_ref: str, scene_dir: Path) -> str:
    """:func:`scene_digest` of a farm run's scene, unpacked from blob ``scene_ref`` (never changed
    once unpacked: computed once per process)."""
    return scene_digest(scene_dir)


@functools.cache
def code_digest() -> str:
    """SHA-256 of the source of ``undream`` and ``scheduler`` as this process runs them (once per process)."""
    h = hashlib.sha256()
    for package in (undream, scheduler):
        root = Path(package.__file__).parent
        h.update(root.name.encode() + b"\0")
        _hash_files(h, root, "*.py")
    return h.hexdigest()


def victim_digest(victim: Any) -> str:
    """SHA-256 of a victim's class, labels, preprocessing, plain settings (thresholds, ...) and every
    parameter and buffer of its torch modules (kept per victim object)."""
    import torch

    if victim in _VICTIM_DIGESTS:
        return _VICTIM_DIGESTS[victim]
    h = hashlib.sha256(f"{type(victim).__module__}.{type(victim).__qualname__}".encode())
    for name, value in sorted(vars(victim).items()):
        if isinstance(value, torch.nn.Module):
            tensors = [*value.named_parameters(), *value.named_buffers()]
            for tname, t in sorted(tensors, key=lambda item: item[0]):
                h.update(f"{name}.{tname}:{t.dtype}:{tuple(t.shape)}".encode())
                h.update(t.detach().cpu().contiguous().numpy().tobytes())
        elif isinstance(value, (str, int, float, bool, tuple, list, type(None))) \
                or hasattr(value, "__dataclass_fields__"):
            h.update(f"{name}={value!r}".encode())
        elif isinstance(value, torch.device):
            h.update(f"{name}={value}".encode())
        elif hasattr(value, "forward_raw"):  # a wrapped victim (a defended victim's inner one)
            h.update(f"{name}:{victim_digest(value)}".encode())
    _VICTIM_DIGESTS[victim] = digest = h.hexdigest()
    return digest


def key_document(ctx: "RunContext", scene: str, texture: np.ndarray) -> dict[str, Any]:
    """Everything that decides a benign frame's image and prediction (see the module docstring).

    ``scene``: the scene's content digest; ``texture``: the benign 8-bit texture (sRGB H×W×3 in [0, 1])."""
    from undream.engine.algorithm import EVAL_ITERATION, EVAL_SEED

    cfg = ctx.config
    return {
        "scene": scene, "texture": array_digest(texture), "frames": ctx.frame_indices,
        "sim": cfg.sim, "sim_versions": ctx.sim.versions(), "frozen": bool(getattr(ctx.scenes, "frozen", True)),
        "eval_spp": cfg.eval_spp, "eval_seed": [EVAL_SEED, EVAL_ITERATION],
        "victim": cfg.victim, "task": ctx.victim.task, "device": cfg.device,
        "victim_weights": victim_digest(ctx.victim),
        "torch_threads": cfg.torch_threads, "victim_batch": cfg.victim_batch,
        "code": code_digest(), "versions": versions(),
    }


def benign_key(document: dict[str, Any]) -> str:
    """The SHA-256 of a key document (canonical JSON)."""
    return hashlib.sha256(json.dumps(document, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@dataclass(frozen=True)
class CachedFrame:
    """One benign frame as kept: its image (H×W×3 uint8 sRGB) and the victim's prediction (JSON)."""

    image: np.ndarray
    prediction: dict[str, Any]


class BenignCache:
    """The benign evaluation's entries of one key in a blob store (see the module docstring)."""

    def __init__(self, blobs: BlobStore, document: dict[str, Any]) -> None:
        self.blobs = blobs
        self.document = document
        self.key = benign_key(document)

    def _entry(self, position: int, suffix: str) -> str:
        return f"{PREFIX}/{self.key}/{position:04d}.{suffix}"

    def get(self, positions: Sequence[int]) -> list[CachedFrame] | None:
        """Every frame of the batch ``positions``, or None unless each is kept and was judged in this batch."""
        out = []
        for p in positions:
            if not self.blobs.exists(self._entry(p, "json")):
                return None
            try:
                meta = self.blobs.get_json(self._entry(p, "json"))
                if meta.get("batch") != list(positions):
                    return None
                out.append(CachedFrame(self.blobs.get_array(self._entry(p, "npy")), meta["prediction"]))
            except (StoreError, KeyError, AttributeError):  # a half-written or foreign entry: compute it again
                return None
        return out

    def put(self, positions: Sequence[int], frames: Sequence[CachedFrame]) -> None:
        """Keep the frames of the batch ``positions`` (each image before its prediction, so an entry
        whose ``.json`` exists is whole)."""
        if not self.blobs.exists(f"{PREFIX}/{self.key}/key.json"):
            self.blobs.put_json(f"{PREFIX}/{self.key}/key.json", self.document)
        for p, frame in zip(positions, frames):
            self.blobs.put_array(self._entry(p, "npy"), frame.image)
            prediction = json.loads(dumps("prediction", frame.prediction))  # as the job rows keep it
            self.blobs.put_json(self._entry(p, "json"), {"prediction": prediction, "batch": list(positions)})


def benign_cache(blobs: BlobStore, ctx: "RunContext", scene_ref: str | None, texture: np.ndarray) -> BenignCache:
    """The cache of a run's benign evaluation (its scene: :func:`scene_digest` of its scene directory;
    on the farm, ``scene_ref``, once per process)."""
    scene = _unpacked_digest(scene_ref, ctx.scene_dir) if scene_ref else scene_digest(ctx.scene_dir)
    return BenignCache(blobs, key_document(ctx, scene, texture))
