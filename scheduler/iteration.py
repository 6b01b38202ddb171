"""One iteration through the store: the per-frame job's task body and the completion callback.

These are what the farm wraps in Celery tasks (a chord of :func:`frame_job`
with :func:`reduce_and_step` as its callback); the in-process runner calls
them in a loop. The math lives in the library (:mod:`undream.engine`,
:mod:`undream.attacks`); here is only reading and writing run state.
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from undream.errors import AttackError, UndreamError

if TYPE_CHECKING:
    from undream.attacks.base import Attack
    from undream.engine.context import RunContext
    from undream.store import Store

log = logging.getLogger(__name__)


def frame_job(store: Store, ctx: RunContext, run_id: str, k: int, position: int) -> dict[str, Any]:
    """Render-and-grad frame ``position`` of iteration ``k`` with the stored texture; store the result.

    Returns the job's small JSON summary (the gradient goes to the blob store).
    """
    from undream.engine.job import render_and_grad

    store.job_started(run_id, k, position)
    try:
        res = render_and_grad(ctx, position, store.texture(run_id, k), k)
    except UndreamError as err:
        store.job_failed(run_id, k, position, str(err))
        raise
    store.job_succeeded(run_id, k, position, res.grad, res.loss, res.finite, res.timings)
    return res.summary()


class AllFramesFailed(UndreamError):
    """Every frame of an iteration produced a non-finite gradient or loss."""


def reduce_and_step(store: Store, attack: Attack, run_id: str, k: int) -> bool:
    """Average iteration ``k``'s finite frame gradients, step the attack, advance the run to ``k + 1``.

    Frames with a NaN/Inf gradient or loss are dropped with a warning and
    counted; when none is left the run fails with :class:`AllFramesFailed`.
    Returns False when the run is no longer at iteration ``k`` (the callback
    already ran): calling it twice never steps twice.
    """
    import torch

    from undream.attacks import average_frames, state_from_dict, state_to_dict

    if store.get_run(run_id).iteration != k:
        return False
    t0 = time.perf_counter()
    rows = store.frame_grads(run_id, k)
    texture = torch.from_numpy(store.texture(run_id, k))
    missing = torch.full_like(texture, float("nan"))  # a failed job counts as a non-finite frame
    grads = [torch.from_numpy(g) if g is not None else missing for _, g, _, _ in rows]
    losses = [float("nan") if loss is None else loss for _, _, loss, _ in rows]
    try:
        G, loss, kept = average_frames(grads, losses)
    except AttackError:
        msg = f"iteration {k}: all {len(rows)} frames gave a non-finite gradient or loss; run stopped"
        store.set_status(run_id, "failed", error=msg)
        raise AllFramesFailed(msg) from None
    dropped = [rows[i][0] for i in range(len(rows)) if i not in kept]
    if dropped:
        log.warning("iteration %d: dropped %d frame(s) with non-finite gradients: %s", k, len(dropped), dropped)
    state = state_from_dict(store.attack_state(run_id, k))
    T_next, state = attack.step(texture, G, loss, state)
    record = {"loss_mean": loss, "n_ok": len(kept), "n_bad": len(dropped), "dropped_frames": dropped,
              "grad_norm": float(G.norm()), "step_seconds": time.perf_counter() - t0}
    return store.advance(run_id, k, T_next.numpy().astype(np.float32), state_to_dict(state), record)
