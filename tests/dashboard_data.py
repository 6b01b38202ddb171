"""A farm's database built through the Store API, for the dashboard's tests and benchmark.

No rendering: textures are tiny random arrays, gradients 2×2×3, frames
small uint8 images. Attack jobs carry the classifier's verdict on their frame
(fewer frames correct as the attack goes on); a run with ``holdout`` renders
its held-out frames in the evaluation only, and its results have the
``attacked`` and ``held_out`` blocks. :func:`build_farm` makes one run in every state
(queued, running, evaluating, done, failed, cancelled) and a sweep over
attack × ε whose runs are done; :func:`add_run` makes one run of any size.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

WORKERS = ("node-a:101", "node-a:102", "node-b:201")
LABELS = ["car", "sphere", "stop_sign", "traffic_cone", "trash_bin", "umbrella"]
TRUE_LABEL = 4  # trash_bin


@dataclass
class RunShape:
    """What :func:`add_run` makes: ``status``; ``done_steps`` of ``steps`` taken; ``frames`` per iteration."""

    name: str
    status: str
    frames: int = 4
    steps: int = 6
    done_steps: int = 0
    attack: str = "pgd"
    eps: float = 32.0
    texture: tuple[int, int] = (16, 32)  # height, width in texels
    frame_px: int = 64
    sweep_id: str | None = None
    error: str | None = None
    holdout: Any = "none"  # as in a run config: "none", "auto" (every 4th frame), {"frames": [...]}
    extra: dict[str, Any] = field(default_factory=dict)


def config(shape: RunShape) -> dict[str, Any]:
    """A run config as the farm stores it (plain JSON)."""
    return {"name": shape.name, "scene": "examples/bin_park.yaml", "victim": "bundled:classifier",
            "loss": "ce", "attack": {"name": shape.attack, "eps": shape.eps, "steps": shape.steps},
            "sim_spp": 16, "grad_spp": 8, "eval_spp": 32, "seed": 0, "holdout": shape.holdout, **shape.extra}


def _grad() -> np.ndarray:
    return np.full((2, 2, 3), 0.01, np.float32)


def _frame(texture: np.ndarray, px: int) -> np.ndarray:
    """A px × px uint8 picture: sky, ground and a box wearing ``texture`` (H×W×3, 0–1)."""
    rows = np.linspace(0.0, 1.0, px)[:, None, None]
    img = np.where(rows < 0.6, [0.55, 0.72, 0.92] + 0.35 * rows, [0.42, 0.45, 0.40]) * np.ones((px, px, 3))
    top, left, size = px // 4, px // 3, px // 2
    yy = np.arange(size) * texture.shape[0] // size
    xx = np.arange(size) * texture.shape[1] // size
    img[top:top + size, left:left + size] = texture[yy][:, xx]
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _texture0(h: int, w: int) -> np.ndarray:
    """A smooth starting texture (sRGB, 0–1): stripes across, a ramp down."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([0.5 + 0.35 * np.sin(2 * np.pi * x / w * 2), y / max(h - 1, 1),
                     np.full((h, w), 0.45)], axis=2).astype(np.float32)


def _strength(shape: RunShape) -> float:
    """The fraction of frames the final texture fools: more at a larger ε (mifgsm a little more)."""
    return min(1.0, shape.eps / 32.0 * (1.0 if shape.attack == "mifgsm" else 0.75))


def _attack_prediction(shape: RunShape, k: int, i: int, n: int) -> dict[str, Any]:
    """The verdict on the ``i``-th of ``n`` attacked frames at iteration ``k``: frames fall one by one."""
    fooled = round(n * _strength(shape) * min(1.0, k / max(1, shape.steps - 1)))
    label = (TRUE_LABEL + 1) % len(LABELS) if i < fooled else TRUE_LABEL
    return {"label": label, "score": 0.8, "correct": label == TRUE_LABEL}


def _iteration(store: Any, run_id: str, k: int, shape: RunShape, rng: np.random.Generator,
               slow: set[tuple[int, int]]) -> float:
    """Iteration ``k``'s attack jobs (attacked frames), all succeeded (``slow`` (k, frame) pairs take
    5× longer); mean loss."""
    frames = attacked(shape)
    store.queue_jobs(run_id, k, frames)
    losses = []
    for i, f in enumerate(frames):
        worker = WORKERS[(k + f) % len(WORKERS)]
        store.job_started(run_id, k, f, worker=worker)
        loss = 0.1 + 3.0 * (1 - np.exp(-k / 3)) + 0.05 * f + 0.01 * float(rng.random())
        total = 0.4 * (5.0 if (k, f) in slow else 1.0) + 0.02 * float(rng.random())
        store.job_succeeded(run_id, k, f, _grad(), loss, True,
                            {"sim_render": total * 0.4, "victim": total * 0.2,
                             "grad_render": total * 0.4, "total": total},
                            result={"prediction": _attack_prediction(shape, k, i, len(frames))})
        losses.append(loss)
    return float(np.mean(losses))


def attacked(shape: RunShape) -> list[int]:
    """The frame positions the attack renders (``shape.holdout``'s held-out ones excluded)."""
    from undream.spec.run import split_frames

    return split_frames(shape.holdout, shape.frames)[0]


def _advance(store: Any, run_id: str, k: int, texture: np.ndarray, loss: float, frames: int,
             seen: np.ndarray) -> np.ndarray:
    step = 0.06 * np.sign(np.sin(texture * 40 + k)) * seen[:, :, None]  # texels no frame sees stay put
    nxt = np.clip(texture + step, 0.0, 1.0).astype(np.float32)
    record = {"loss_mean": loss, "n_ok": frames, "n_bad": 0, "dropped_frames": [],
              "grad_norm": 0.5 + 0.1 * k, "step_seconds": 0.01}
    assert store.advance(run_id, k, nxt, {"t": k + 1}, record)
    return nxt


def _evaluate(store: Any, run_id: str, shape: RunShape, texture: np.ndarray, phase: str,
              labels: list[int]) -> None:
    k = shape.done_steps
    store.queue_jobs(run_id, k, range(shape.frames), phase)
    for f in range(shape.frames):
        store.job_started(run_id, k, f, phase, worker=WORKERS[f % len(WORKERS)])
        store.eval_succeeded(run_id, k, f, phase, {"prediction": {"label": labels[f], "score": 0.9}},
                             _frame(texture, shape.frame_px), {"total": 0.3})


def _adversarial_labels(shape: RunShape) -> list[int]:
    """Predictions on the adversarial frames: more frames fooled at a larger ε (mifgsm a little more)."""
    fooled = round(shape.frames * _strength(shape))
    return [(TRUE_LABEL + 1 + f % 2) % len(LABELS) if f < fooled else TRUE_LABEL for f in range(shape.frames)]


def _accuracy(preds: list[int]) -> float:
    return float(np.mean([p == TRUE_LABEL for p in preds]))


def _split(positions: list[int], benign: list[int], adv: list[int]) -> dict[str, Any] | None:
    """results.json's ``attacked`` / ``held_out`` block of the frames at ``positions``."""
    if not positions:
        return None
    b, a = [benign[i] for i in positions], [adv[i] for i in positions]
    return {"frames": positions, "benign": {"metric": "accuracy", "value": _accuracy(b)},
            "adversarial": {"metric": "accuracy", "value": _accuracy(a)},
            "attack_success": {"success_rate": float(np.mean([p != TRUE_LABEL for p in a]))}}


def _results(shape: RunShape, losses: list[float], benign: list[int], adv: list[int]) -> dict[str, Any]:
    from undream.spec.run import split_frames

    def judged(preds: list[int]) -> dict[str, Any]:
        rows = [{"frame": f, "prediction": p, "class": LABELS[p], "correct": p == TRUE_LABEL}
                for f, p in enumerate(preds)]
        return {"metric": "accuracy", "value": _accuracy(preds), "per_frame": rows}
    fooled = float(np.mean([p != TRUE_LABEL for p in adv]))
    attacked_at, held = split_frames(shape.holdout, shape.frames)
    return {"task": "classification", "victim": "bundled:classifier", "label": LABELS[TRUE_LABEL],
            "attack": {"name": shape.attack, "eps": shape.eps}, "benign": judged(benign),
            "adversarial": judged(adv), "attack_success": {"aggregate": {"success_rate": fooled}},
            "attacked": _split(attacked_at, benign, adv), "held_out": _split(held, benign, adv),
            "loss_per_iteration": losses}


def add_run(store: Any, shape: RunShape, rng: np.random.Generator) -> str:
    """One run in ``shape.status`` with ``shape.done_steps`` iterations taken; returns its id."""
    h, w = shape.texture
    T0 = _texture0(h, w)
    visible = np.zeros((h, w), bool)
    visible[:, : w * 3 // 4] = True  # the last quarter of the texels: no frame sees them
    started = shape.status != "queued"
    run_id = store.create_run(shape.name, config(shape), shape.frames, 0,
                              texture0=T0 if started else None,
                              attack_state0={"t": 0} if started else None,
                              arrays0={"T0": T0, "visible": visible} if started else None,
                              sweep_id=shape.sweep_id)
    if not started:
        return run_id
    store.set_status(run_id, "running")
    texture, losses = T0, []
    slow = {(1, shape.frames - 1), (shape.done_steps // 2, 0)}
    for k in range(shape.done_steps):
        losses.append(_iteration(store, run_id, k, shape, rng, slow))
        texture = _advance(store, run_id, k, texture, losses[-1], len(attacked(shape)), visible)
    if shape.status in ("running", "failed", "cancelled"):
        _current_iteration(store, run_id, shape)
    if shape.status in ("evaluating", "done"):
        store.set_status(run_id, "evaluating")
        benign = [TRUE_LABEL] * shape.frames
        adv = _adversarial_labels(shape)
        _evaluate(store, run_id, shape, T0, "pre", benign)
        final = (np.round(texture * 255) / 255).astype(np.float32)
        store.put_final_texture(run_id, final)
        if shape.status == "done":
            _evaluate(store, run_id, shape, final, "adversarial", adv)
            store.set_results(run_id, _results(shape, losses, benign, adv))
            store.set_status(run_id, "done")
    if shape.status in ("failed", "cancelled"):
        error = shape.error or ("cancelled by the user" if shape.status == "cancelled" else
                                f"frame 1 of iteration {shape.done_steps} failed 3 times")
        store.set_status(run_id, shape.status, error=error)
    return run_id


def _current_iteration(store: Any, run_id: str, shape: RunShape) -> None:
    """The unfinished iteration of an active (or stopped) run: done, failed, retried, started, queued jobs."""
    k = shape.done_steps
    store.queue_jobs(run_id, k, attacked(shape))
    for f in attacked(shape):
        worker = WORKERS[f % len(WORKERS)]
        if f == 0:
            store.job_started(run_id, k, f, worker=worker)
            store.job_succeeded(run_id, k, f, _grad(), 0.5, True, {"total": 0.41},
                                result={"prediction": _attack_prediction(shape, k, 0, len(attacked(shape)))})
        elif f == 1:
            store.job_started(run_id, k, f, worker=worker)
            store.job_failed(run_id, k, f, "RenderError: Mitsuba ran out of memory on frame 1",
                             will_retry=shape.status == "running")
        elif f == 2:
            store.job_started(run_id, k, f, worker=worker)


@dataclass
class Farm:
    """The ids :func:`build_farm` made: one run per state, the sweep and its runs."""

    runs: dict[str, str]
    sweep_id: str
    sweep_runs: list[str]


def build_farm(store: Any, seed: int = 0, frames: int = 4, steps: int = 6) -> Farm:
    """One run in every state and a sweep (pgd and mifgsm × ε 8, 16, 32) of done runs."""
    rng = np.random.default_rng(seed)
    runs = {}
    plan = {"queued": 0, "running": steps // 2, "evaluating": steps, "done": steps,
            "failed": steps // 2, "cancelled": 1}
    for status, done_steps in plan.items():
        holdout = "auto" if status == "done" else "none"  # the done run holds frame 3 out
        runs[status] = add_run(store, RunShape(f"bin-{status}", status, frames, steps, done_steps,
                                               holdout=holdout), rng)
    spec = {"name": "eps-sweep", "run": "runs/bin_park_pgd.yaml",
            "grid": {"attack.name": ["pgd", "mifgsm"], "attack.eps": [8, 16, 32]}}
    sweep_id = store.create_sweep("eps-sweep", spec)
    sweep_runs = []
    for i, (attack, eps) in enumerate((a, e) for a in ("pgd", "mifgsm") for e in (8, 16, 32)):
        shape = RunShape(f"eps-sweep-{i:03d}", "done", frames, 3, 3, attack=attack, eps=float(eps),
                         sweep_id=sweep_id, holdout="auto")
        sweep_runs.append(add_run(store, shape, rng))
    return Farm(runs, sweep_id, sweep_runs)


def _detector_prediction(f: int, px: int, found: bool) -> dict[str, Any]:
    """A detector's evaluation prediction as a job row keeps it (scheduler.evaluation): the raw output
    and the boxes a page draws; the object's box is the picture's textured square (:func:`_frame`)."""
    top, left, size = px // 4, px // 3, px // 2
    truth = [float(left), float(top), float(left + size), float(top + size)]
    dets = [{"box": [truth[0] + 1, truth[1] + 2, truth[2] - 1, truth[3]], "score": 0.87, "label": "trash bin"},
            {"box": [2.0, 2.0, px / 4, px / 5], "score": 0.31, "label": "car"}] if found else \
        [{"box": [2.0, 2.0, px / 4, px / 5], "score": 0.42, "label": "umbrella"}]
    return {"boxes": [d["box"] for d in dets], "scores": [d["score"] for d in dets],
            "labels": [LABELS.index(d["label"].replace(" ", "_")) for d in dets], "detected": found,
            "detections": dets, "truth_box": truth, "truth_label": "trash bin", "size": [px, px]}


def add_detector_run(store: Any, name: str = "bin-detector", frames: int = 2, px: int = 64) -> str:
    """A done run against a detector whose evaluation frames carry boxes: every benign frame found,
    every adversarial one missed; returns its id."""
    shape = RunShape(name, "done", frames=frames, steps=1, frame_px=px,
                     extra={"victim": "coco:centernet", "loss": "vanish"})
    T0 = _texture0(*shape.texture)
    run_id = store.create_run(name, config(shape), frames, 0, texture0=T0, attack_state0={"t": 0},
                              arrays0={"T0": T0})
    store.set_status(run_id, "running")
    store.set_status(run_id, "evaluating")
    store.put_final_texture(run_id, T0)
    for phase, found in (("pre", True), ("adversarial", False)):
        store.queue_jobs(run_id, 0, range(frames), phase)
        for f in range(frames):
            store.job_started(run_id, 0, f, phase, worker=WORKERS[0])
            store.eval_succeeded(run_id, 0, f, phase, {"prediction": _detector_prediction(f, px, found)},
                                 _frame(T0, px), {"total": 0.3})
    store.set_results(run_id, {"task": "detection", "victim": "coco:centernet", "label": "trash bin",
                               "benign": {"metric": "ap50", "value": 1.0},
                               "adversarial": {"metric": "ap50", "value": 0.0}})
    store.set_status(run_id, "done")
    return run_id
