"""One iteration through the store: the per-frame job's body and the reduce-and-step callback.

The farm runs :func:`frame_jobs` inside its per-frame-batch tasks (the
chord's header) and :func:`reduce_and_step` in the chord's callback
(:mod:`scheduler.stages`); ``undream run`` calls the same functions in one
process. The math lives in the library (:mod:`undream.engine`,
:mod:`undream.attacks`); here is only reading and writing run state.
"""
from __future__ import annotations

import logging
import os
import socket
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from scheduler.state import decode_state, encode_state
from undream.errors import AttackError, StoreError, UndreamError
from scheduler.options import attacked_frames  # noqa: F401  (re-exported: tests and readers import it here)

if TYPE_CHECKING:
    from undream.attacks.base import Attack
    from undream.engine.context import RunContext
    from undream.printing.gamut import Gamut
    from undream.store import RunSnapshot, Store

log = logging.getLogger(__name__)


class AllFramesFailed(UndreamError):
    """Every frame of an iteration produced a non-finite gradient or loss."""


class MissingResults(UndreamError):
    """An iteration's expected frame jobs have no result yet: reduce refuses to step."""

    def __init__(self, run_id: str, k: int, frames: list[int]) -> None:
        super().__init__(f"run {run_id!r} iteration {k}: no result yet for frame(s) "
                         f"{', '.join(map(str, frames))}; not stepping on fewer frames")
        self.frames = frames


def expected_frames(run: "RunSnapshot", frames_per_step: int | None, k: int) -> list[int]:
    """The frame positions of iteration ``k``: every attacked frame, or the run's seeded minibatch
    of them; never a held-out frame."""
    from undream.engine.algorithm import plan

    return plan(attacked_frames(run), frames_per_step, k, run.seed)


def worker_name() -> str:
    """``host:pid`` of this process (recorded with each job it starts)."""
    return f"{socket.gethostname()}:{os.getpid()}"


def frame_jobs(store: "Store", ctx: "RunContext", run_id: str, k: int, positions: list[int],
               texture: np.ndarray | None = None) -> list[dict[str, Any]]:
    """Render-and-grad frames ``positions`` of iteration ``k`` with texture ``k``; store the results.

    The frames are computed together (:func:`undream.engine.algorithm.frame_jobs`: the victim once
    per batch) and recorded in one transaction each for their start and their results.
    ``texture``: texture ``k`` when the caller already holds it. Returns each job's small JSON
    summary (the gradients go to the blob store); a job's row keeps the victim's prediction on the
    frame it rendered at ``sim_spp`` (``{"prediction": ...}``, see
    :func:`undream.engine.job.prediction_record`), from which the dashboard charts accuracy per
    iteration. Errors propagate: the caller records the failed attempt of every frame.
    """
    from undream.engine.algorithm import frame_jobs as render_and_grad
    from undream.store import JobResult

    store.jobs_started(run_id, k, positions, worker=worker_name())
    res = render_and_grad(ctx, positions, store.texture(run_id, k) if texture is None else texture, k)
    store.jobs_succeeded(run_id, k, [JobResult(frame=f, grad=r.grad, loss=r.loss, finite=r.finite,
                                               timings=r.timings, result={"prediction": r.prediction})
                                     for f, r in zip(positions, res)])
    return [r.summary() for r in res]


def reduce_and_step(store: "Store", attack: "Attack", run_id: str, k: int, gamut: "Gamut | None" = None) -> bool:
    """Average iteration ``k``'s finite frame gradients, step the attack, advance the run to ``k + 1``.

    Refuses (:class:`MissingResults`) while an expected frame job has no
    result: a job that never ran or failed is never averaged away. Frames with
    a NaN/Inf gradient or loss, or recorded not finite (a NaN in the victim's
    image gradient, see :func:`undream.engine.job.render_and_grad`), are
    dropped from both means with a warning and counted (``n_bad``); when
    none is left the run fails with :class:`AllFramesFailed`. Returns False
    when the run is no longer at iteration ``k`` or no longer active (the
    callback already ran, or the run was cancelled): calling it twice never
    steps twice. ``gamut``: the run's printer gamut (``RunContext.gamut``), the step projected into it.
    The attack steps on the run's objective (:func:`undream.engine.algorithm.objective`:
    the victim's loss less its regularisers), whose named terms the iteration record keeps.

    Once it advanced the run, iteration ``k``'s gradients are transient: the
    caller deletes them (:func:`drop_gradients`) once the next iteration's jobs
    are out, so the deletion is not in the gap between iterations; at ``k = 0``
    the texels the frames see are kept first
    (:meth:`undream.store.Store.put_seen_mask`, the dashboard's mask). A caller
    killed between the advance and the deletion leaves garbage only: a retry
    finds the run past ``k``, needs no gradient, and deletes them.
    """
    from undream.engine.algorithm import objective, reduce, step
    from undream.store import ACTIVE

    run = store.get_run(run_id)
    if run.iteration != k or run.status not in ACTIVE:
        if run.iteration > k:  # reduced before: what a caller killed after advancing left behind
            drop_gradients(store, run_id, k)
        return False
    t0 = time.perf_counter()
    expected = expected_frames(run, attack.config.frames_per_step, k)
    try:
        rows = {g.frame: g for g in store.frame_grads(run_id, k)}
    except StoreError:  # a gradient gone: another callback reduced k and deleted them meanwhile
        if store.get_run(run_id).iteration > k:
            return False
        raise
    missing = [f for f in expected if f not in rows or rows[f].grad is None]
    if missing:
        raise MissingResults(run_id, k, missing)
    try:
        G, loss, kept = reduce([rows[f].grad for f in expected], [rows[f].loss for f in expected],
                               [rows[f].finite for f in expected], attack.config.frame_weights)
    except AttackError:
        msg = f"iteration {k}: all {len(expected)} frames gave a non-finite gradient or loss; run stopped"
        store.set_status(run_id, "failed", error=msg)
        raise AllFramesFailed(msg) from None
    dropped = [expected[i] for i in range(len(expected)) if i not in kept]
    if dropped:
        log.warning("iteration %d: dropped %d frame(s) with non-finite gradients: %s", k, len(dropped), dropped)
    state = decode_state(store.attack_state(run_id, k) or {})
    texture = store.texture(run_id, k)
    G, value, terms = objective(run.run_config, texture, G, loss, state)  # the regularisers subtracted
    T_next, state = step(attack, texture, G, value, state, gamut)
    scalars, arrays = encode_state(state)
    record = {"loss_mean": loss, "n_ok": len(kept), "n_bad": len(dropped), "dropped_frames": dropped,
              "grad_norm": float(G.norm()), "step_seconds": time.perf_counter() - t0, "terms": terms}
    if k == 0:
        seen = seen_texels([rows[f].grad for f in expected])
        if seen is not None:
            store.put_seen_mask(run_id, seen)
    return store.advance(run_id, k, T_next, scalars, record, arrays)  # the caller then drops k's gradients


def seen_texels(grads: list[Any]) -> np.ndarray | None:
    """H×W bool: texels where some frame's gradient (H×W×3) is not zero; None without such gradients."""
    seen = None
    for grad in grads:
        if grad is None or np.ndim(grad) != 3:
            continue
        hit = np.any(np.asarray(grad) != 0, axis=2)
        seen = hit if seen is None else (seen | hit if seen.shape == hit.shape else seen)
    return seen


def drop_gradients(store: "Store", run_id: str, k: int | None = None) -> None:
    """Delete iteration ``k``'s frame gradients (None: all the run's), which nothing reads once it is
    reduced; a failure is logged, not raised (the blobs are garbage, not state)."""
    try:
        store.drop_gradients(run_id, k)
    except StoreError as err:
        log.warning("run %s: could not delete the gradients of %s: %s", run_id,
                    "every iteration" if k is None else f"iteration {k}", err)
