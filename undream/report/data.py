"""A finished run as plain data for its report, read through the store (no drawing here).

Frames are H×W×3 uint8 sRGB (the evaluation renders, as in ``frames_benign/``
and ``frames_adversarial/``); textures H×W×3 float sRGB in [0, 1], 8-bit
quantised as the evaluation rendered them; metric values fractions in [0, 1].
A frame has a *position* (0 … n−1, the store's job number) and an *index*
(its number in file names and in results.json).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from undream.color import to_uint8
from undream.errors import StoreError

if TYPE_CHECKING:
    from undream.store import JobSnapshot, RunSnapshot, Store

SPLITS = ("attacked", "held_out")
MAX_BOXES = 5  # a detector's boxes drawn per picture (results.json keeps as many)
PHASES = {"benign": "pre", "adversarial": "adversarial"}  # side → the evaluation jobs' phase


Box = tuple[float, float, float, float]  # x0, y0, x1, y1 in frame pixels


@dataclass(frozen=True)
class Detection:
    """One box a detector kept: frame pixels, its score (0–1) and class name (None: not recorded)."""

    box: Box
    score: float
    label: str | None


@dataclass(frozen=True)
class Side:
    """One evaluation of a frame: its render, the results.json per-frame row, a detector's boxes (at
    most :data:`MAX_BOXES`, highest score first) and the object's true box (None: unseen or unknown)."""

    image: np.ndarray  # H×W×3 uint8 sRGB
    row: dict[str, Any]  # {"prediction", "class", "score", "correct"} or {"detected", "n_detections", "score", ...}
    boxes: list[Detection] = field(default_factory=list)
    truth: Box | None = None


@dataclass(frozen=True)
class FrameData:
    """One frame of the run: benign and adversarial evaluation, and whether the attack saw it."""

    position: int
    index: int
    held_out: bool
    benign: Side
    adversarial: Side


@dataclass(frozen=True)
class Seen:
    """Texels some frame sees (H×W bool, None when unknown) and how that was found (a sentence)."""

    mask: np.ndarray | None
    how: str


@dataclass(frozen=True)
class RunData:
    """Everything a run's report shows (see the module docstring for units)."""

    run: "RunSnapshot"
    results: dict[str, Any]
    frames: list[FrameData]
    texture0: np.ndarray  # the benign texture (the scene's, T0)
    texture_final: np.ndarray  # the adversarial texture that was evaluated
    seen: Seen
    iterations: list[dict[str, Any]]  # per attack step: k, loss_mean, n_bad

    @property
    def task(self) -> str:
        return str(self.results.get("task") or "classification")

    @property
    def label(self) -> str:
        return str(self.results.get("label") or "")


def check_done(run: "RunSnapshot") -> dict[str, Any]:
    """The results of a finished run; StoreError naming the run and its status otherwise."""
    if run.status != "done" or not run.results:
        why = f": {' '.join(run.error.split())}" if run.error else ""
        raise StoreError(f"run {run.id} ({run.name}) is {run.status}{why}; a report needs a finished run "
                         "(status done, with results)")
    return run.results


def held_out_indices(results: dict[str, Any]) -> set[int]:
    """Frame indices the attack never rendered for a gradient (results.json ``held_out`` and
    ``held_out_conditions``)."""
    blocks = [results.get("held_out") or {}, results.get("held_out_conditions") or {}]
    return {int(i) for block in blocks for i in block.get("frames") or []}


def _jobs(store: "Store", run: "RunSnapshot", side: str) -> dict[int, "JobSnapshot"]:
    jobs = {j.frame: j for j in store.jobs(run.id, run.iteration, PHASES[side])}
    missing = [f for f in range(run.n_frames) if f not in jobs or jobs[f].status != "succeeded"
               or not jobs[f].image_ref]
    if missing:
        raise StoreError(f"run {run.id} ({run.name}): no {side} evaluation frame at positions {missing} "
                         "in the store")
    return jobs


def _side(store: "Store", job: "JobSnapshot", row: dict[str, Any]) -> Side:
    image = store.blobs.get_array(job.image_ref)  # type: ignore[arg-type]
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise StoreError(f"run {job.run_id}: frame {job.frame}: expected an H×W×3 uint8 image, "
                         f"got {image.dtype} {image.shape}")
    truth = row.get("truth_box")
    return Side(image, row, detections(row, (job.result or {}).get("prediction") or {}),
                None if not truth else _box(truth))


def _box(values: Any) -> Box:
    x0, y0, x1, y1 = (float(v) for v in values)
    return x0, y0, x1, y1


def detections(row: dict[str, Any], prediction: dict[str, Any]) -> list[Detection]:
    """A frame's boxes: the results.json row's ``boxes`` (class names, after the victim's threshold and
    NMS); for results written before rows held them, the stored prediction's (no class names)."""
    if "boxes" in row:
        return [Detection(_box(d["box"]), float(d["score"]), d.get("label")) for d in row["boxes"] or []]
    boxes, scores = prediction.get("boxes") or [], prediction.get("scores") or []
    dets = [Detection(_box(b), float(s), None) for b, s in zip(boxes, scores)]
    return sorted(dets, key=lambda d: -d.score)[:MAX_BOXES]


def frames_of(store: "Store", run: "RunSnapshot", results: dict[str, Any]) -> list[FrameData]:
    """Every frame of the run in position order, with its benign and adversarial evaluation."""
    rows = {side: (results.get(side) or {}).get("per_frame") or [] for side in PHASES}
    for side, per_frame in rows.items():
        if len(per_frame) != run.n_frames:
            raise StoreError(f"run {run.id} ({run.name}): results.{side}.per_frame has {len(per_frame)} "
                             f"rows for {run.n_frames} frames")
    jobs = {side: _jobs(store, run, side) for side in PHASES}
    held = held_out_indices(results)
    frames = []
    for p in range(run.n_frames):
        index = int(rows["benign"][p]["frame"])
        frames.append(FrameData(p, index, index in held,
                                _side(store, jobs["benign"][p], rows["benign"][p]),
                                _side(store, jobs["adversarial"][p], rows["adversarial"][p])))
    return frames


def textures_of(store: "Store", run: "RunSnapshot") -> tuple[np.ndarray, np.ndarray]:
    """(benign T0, evaluated final texture), both 8-bit quantised sRGB in [0, 1]."""
    final = store.final_texture(run.id)
    if final is None:
        where = getattr(store.blobs, "root", "the blob store")
        hint = (" (its blobs are where the farm's UNDREAM_BLOB_URL / --blobs pointed: is that this folder?)"
                if run.status == "done" else f" (status {run.status})")
        raise StoreError(f"run {run.id} ({run.name}): no final texture under {where}{hint}")
    state0 = store.attack_state(run.id, 0) or {}
    start = state0.get("T0")
    if not isinstance(start, np.ndarray):
        start = store.texture(run.id, 0)
    return to_uint8(start).astype(np.float32) / 255.0, to_uint8(final).astype(np.float32) / 255.0


def iterations_of(store: "Store", run: "RunSnapshot") -> list[dict[str, Any]]:
    """Per attack step: k, the mean loss over the kept frames (None when none) and frames dropped."""
    return [{"k": r.k, "loss_mean": r.loss_mean, "n_bad": r.n_bad} for r in store.iterations(run.id)]


def load_run(store: "Store", run: "RunSnapshot", seen_of: Callable[["RunSnapshot", np.ndarray], Seen]) -> RunData:
    """The run's report data; StoreError naming the run when it is not finished or lacks a piece.

    ``seen_of(run, texture0)``: the texels some frame sees (:class:`undream.report.seen.SeenFinder`).
    """
    results = check_done(run)
    texture0, final = textures_of(store, run)
    frames = frames_of(store, run, results)
    return RunData(run, results, frames, texture0, final, seen_of(run, texture0), iterations_of(store, run))
