"""The evaluation's per-frame jobs and the pick of the final texture, through the store.

Two phases of per-frame jobs, each frame rendered at ``eval_spp`` with the
evaluation seed (:func:`undream.engine.algorithm.eval_render`, the one evaluation path
`undream run`, the farm, the baseline and the scripts share):

- ``pre``: the benign frame (the scene's texture, 8-bit) and its prediction,
  and the attack loss of the last iteration's texture (APGD's final pick
  needs it);
- ``adversarial``: the frame with the final 8-bit texture and its prediction.

Predictions are stored as JSON in the job rows and frames as uint8 blobs;
nothing is held in memory between jobs.
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
    from undream.engine.context import RunContext
    from undream.store import Store


def prediction_json(ctx: "RunContext", image: np.ndarray) -> dict[str, Any]:
    """The victim's prediction on one sRGB frame as plain JSON (class id and score, or boxes)."""
    from undream.engine.algorithm import eval_predict

    return eval_predict(ctx, image).to_dict()


def prediction_from_json(task: str, data: dict[str, Any]) -> Any:
    """A stored prediction in the shape the metrics read (``.label`` and its ``.score``, or
    ``.boxes/.scores/.labels``)."""
    if task == "classification":
        score = data.get("score")
        return SimpleNamespace(label=int(data["label"]), score=None if score is None else float(score))
    return SimpleNamespace(boxes=np.asarray(data["boxes"], np.float64).reshape(-1, 4),
                           scores=np.asarray(data["scores"], np.float64),
                           labels=np.asarray(data["labels"], np.int64))


def eval_job(store: "Store", ctx: "RunContext", run_id: str, phase: str, k: int, position: int,
             textures: dict[str, np.ndarray]) -> None:
    """Evaluation job of frame ``position`` in ``phase`` (see the module docstring); k = the steps.

    ``textures``: ``benign`` and ``last`` for ``pre``, ``final`` for
    ``adversarial`` (sRGB H×W×3; the caller reads them once per batch).
    """
    from undream.engine.algorithm import eval_loss, eval_render

    store.job_started(run_id, k, position, phase, worker=worker_name())
    t0 = time.perf_counter()
    if phase == "pre":
        image = eval_render(ctx, position, textures["benign"])
        result = {"prediction": prediction_json(ctx, image),
                  "loss": eval_loss(ctx, position, eval_render(ctx, position, textures["last"]))}
    else:
        image = eval_render(ctx, position, textures["final"])
        result = {"prediction": prediction_json(ctx, image)}
    store.eval_succeeded(run_id, k, position, phase, result, to_uint8(image),
                         {"total": time.perf_counter() - t0})


def eval_textures(store: "Store", run_id: str, phase: str, k: int) -> dict[str, np.ndarray]:
    """The textures the evaluation jobs of ``phase`` render (see :func:`eval_job`)."""
    from undream.engine.algorithm import quantise

    if phase == "pre":
        state0 = store.attack_state(run_id, 0) or {}
        if not isinstance(state0.get("T0"), np.ndarray):
            raise StoreError(f"run {run_id!r}: its starting attack state has no T0 array")
        return {"benign": quantise(state0["T0"]), "last": store.texture(run_id, k)}
    final = store.final_texture(run_id)
    if final is None:
        raise StoreError(f"run {run_id!r}: no final texture yet (the 'pre' evaluation has not finished)")
    return {"final": final}


def select_final(store: "Store", attack: Any, run_id: str, k: int) -> np.ndarray:
    """Pick the texture to report after the last step (``Attack.final``), quantised to 8 bits."""
    import torch

    from undream.engine.algorithm import quantise

    losses = [float("nan") if (j.result or {}).get("loss") is None else j.result["loss"]  # type: ignore[index]
              for j in store.jobs(run_id, k, "pre")]
    final_loss = float(np.mean(losses))
    T_last = store.texture(run_id, k)
    T_final = attack.final(torch.from_numpy(T_last), final_loss,
                           decode_state(store.attack_state(run_id, k) or {})).numpy()
    return quantise(T_final)
