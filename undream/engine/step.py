"""Reduce-and-step: the completion callback of one iteration, idempotent by compare-and-set."""
from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from undream.errors import AttackError, UndreamError

log = logging.getLogger(__name__)


class AllFramesFailed(UndreamError):
    """Every frame of an iteration produced a non-finite gradient or loss."""


def reduce_and_step(store: Any, attack: Any, run_id: str, k: int) -> bool:
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
