"""The evaluation's per-frame jobs and the pick of the final texture, through the store.

Two phases of per-frame jobs, each frame rendered at ``eval_spp`` with the
evaluation seed (:func:`undream.engine.algorithm.eval_render`, the one evaluation path
`undream run`, the farm, the baseline and the scripts share):

- ``pre``: the benign frame (the scene's texture, 8-bit) and its prediction,
  and, when the attack's final pick needs it (APGD), the attack loss of the
  last iteration's texture;
- ``adversarial``: the frame with the final 8-bit texture and its prediction.

The benign half of ``pre`` is the same for every run of a sweep over seeds,
budgets or attacks: it is read from the blob store when a run with the same
key kept it there (:mod:`scheduler.benign`). A batch of jobs renders its
frames, runs the victim once per batch of frames and records the results in
one transaction. Predictions are stored
as JSON in the job rows and frames as uint8 blobs; nothing is held in memory
between batches.
"""
from __future__ import annotations

import time
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from scheduler.iteration import worker_name
from scheduler.state import decode_state
from undream.color import to_uint8
from undream.errors import StoreError

if TYPE_CHECKING:
    from scheduler.benign import BenignCache, CachedFrame
    from undream.engine.context import RunContext
    from undream.store import Store


def prediction_from_json(task: str, data: dict[str, Any]) -> Any:
    """A stored prediction in the shape the metrics read (``.label`` and its ``.score``, or
    ``.boxes/.scores/.labels``)."""
    if task == "classification":
        score = data.get("score")
        return SimpleNamespace(label=int(data["label"]), score=None if score is None else float(score))
    return SimpleNamespace(boxes=np.asarray(data["boxes"], np.float64).reshape(-1, 4),
                           scores=np.asarray(data["scores"], np.float64),
                           labels=np.asarray(data["labels"], np.int64))


def eval_jobs(store: "Store", ctx: "RunContext", run_id: str, phase: str, k: int, positions: list[int],
              textures: dict[str, np.ndarray], benign: "BenignCache | None" = None) -> None:
    """Evaluation jobs of frames ``positions`` in ``phase`` (see the module docstring); k = the steps.

    Each frame is rendered, the victim judges them once per batch of frames, and the results
    are recorded in one transaction. ``textures``: ``benign`` (and ``last`` when the attack's final
    pick reads the last texture's loss, :attr:`undream.attacks.base.Attack.needs_final_loss`) for
    ``pre``, ``final`` for ``adversarial`` (sRGB H×W×3; the caller reads them once per batch).
    ``benign``: the cache of the ``pre`` phase's benign frames (:mod:`scheduler.benign`): read
    when it holds the whole batch, written when it does not; each job's result says which
    (``benign_cache``: the key and ``hit``). None: rendered and judged here, as always.
    """
    from undream.engine.algorithm import eval_losses, eval_render
    from undream.store import EvalResult

    store.jobs_started(run_id, k, positions, phase, worker=worker_name())
    t0 = time.perf_counter()
    results, images = _judged_frames(ctx, positions, textures["benign" if phase == "pre" else "final"],
                                      benign if phase == "pre" else None)
    if phase == "pre" and "last" in textures:
        losses = eval_losses(ctx, positions, [eval_render(ctx, p, textures["last"]) for p in positions])
        for result, loss in zip(results, losses):
            result["loss"] = loss
    share = (time.perf_counter() - t0) / len(positions)
    store.evals_succeeded(run_id, k, phase, [EvalResult(frame=p, result=r, image=im, timings={"total": share})
                                             for p, r, im in zip(positions, results, images)])


def _judged_frames(ctx: "RunContext", positions: list[int], texture: np.ndarray,
                   benign: "BenignCache | None") -> tuple[list[dict[str, Any]], list[np.ndarray]]:
    """Each frame's result (``prediction``) and image (H×W×3 uint8 sRGB) with ``texture``: from the
    cache ``benign`` when it holds the whole batch, else rendered and judged (and kept in ``benign``)."""
    from scheduler.benign import CachedFrame
    from undream.engine.algorithm import eval_predictions, eval_render

    kept = benign.get(positions) if benign is not None else None
    hit = kept is not None
    if kept is None:
        rendered = [eval_render(ctx, p, texture) for p in positions]
        kept = [CachedFrame(to_uint8(im), pred.to_dict())
                for im, pred in zip(rendered, eval_predictions(ctx, rendered))]
        if benign is not None:
            benign.put(positions, kept)
    results: list[dict[str, Any]] = [{"prediction": _drawable(ctx, p, f)} for p, f in zip(positions, kept)]
    if benign is not None:
        for result in results:
            result["benign_cache"] = {"key": benign.key, "hit": hit}
    return results, [f.image for f in kept]


def _drawable(ctx: "RunContext", position: int, frame: "CachedFrame") -> dict[str, Any]:
    """A frame's prediction as its job row keeps it: the victim's output (``pred.to_dict()``, what
    the results are computed from) and, for a detector, what the dashboard draws on the frame
    (:func:`undream.engine.job.detection_boxes`, and ``size``: the frame's width and height in px)."""
    if ctx.victim.task == "classification":
        return frame.prediction
    h, w = frame.image.shape[:2]
    from undream.engine.job import detection_boxes  # torch: not in the worker's parent process

    drawn = detection_boxes(ctx, position, prediction_from_json("detection", frame.prediction))
    return {**frame.prediction, **drawn, "size": [int(w), int(h)]}


def eval_textures(store: "Store", run_id: str, phase: str, k: int,
                  needs_final_loss: bool = True) -> dict[str, np.ndarray]:
    """The textures the evaluation jobs of ``phase`` render (see :func:`eval_jobs`); ``last`` only
    when ``needs_final_loss`` (the attack's final pick reads the last texture's loss)."""
    from undream.engine.algorithm import quantise

    if phase == "pre":
        state0 = store.attack_state(run_id, 0) or {}
        if not isinstance(state0.get("T0"), np.ndarray):
            raise StoreError(f"run {run_id!r}: its starting attack state has no T0 array")
        benign = {"benign": quantise(state0["T0"])}
        return {**benign, "last": store.texture(run_id, k)} if needs_final_loss else benign
    final = store.final_texture(run_id)
    if final is None:
        raise StoreError(f"run {run_id!r}: no final texture yet (the 'pre' evaluation has not finished)")
    return {"final": final}


def select_final(store: "Store", attack: Any, run_id: str, k: int) -> np.ndarray:
    """Pick the texture to report after the last step (``Attack.final``), quantised to 8 bits; the last
    texture's value is its objective as the steps saw it (the victim's loss less the regularisers)."""
    import torch

    from undream.engine.algorithm import objective_value, quantise

    losses = [float("nan") if (j.result or {}).get("loss") is None else j.result["loss"]  # type: ignore[index]
              for j in store.jobs(run_id, k, "pre")]
    final_loss = float(np.mean(losses)) if losses else float("nan")  # NaN: not measured (not needed)
    T_last = store.texture(run_id, k)
    final_loss = objective_value(store.get_run(run_id).run_config, T_last, final_loss)  # its steps' objective
    T_final = attack.final(torch.from_numpy(T_last), final_loss,
                           decode_state(store.attack_state(run_id, k) or {})).numpy()
    return quantise(T_final)
