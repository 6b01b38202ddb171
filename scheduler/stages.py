"""A run in stages keyed by its id: start → iterate → evaluate → finish.

Every stage is a plain function of the store (and, where it renders, a
function giving the run's context); the stage that closes a phase hands the
next one to a :class:`Dispatch`. On the farm that is Celery (``workers/``): a
chord per phase whose header runs :func:`run_batch` on batches of frames and
whose callback runs :func:`collect`; ``undream run`` drains the same calls
from a queue in one process (:mod:`scheduler.local`). Nothing else drives a
run: no scheduler daemon; :func:`resume` re-dispatches a run from what the
store says after any crash.

Phases of per-frame jobs (the store's job ``phase``):

=============  ======================================  =====================================
phase          one job                                 collect, when every job has a result
=============  ======================================  =====================================
``attack`` k   render and gradient of frame f at T_k   reduce and step → plan k + 1, or ``pre``
``pre``        benign frame + loss at T_N              pick the final texture → ``adversarial``
``adversarial``  frame with the final texture          results and outputs; the run is done
=============  ======================================  =====================================

A job that raises is retried up to ``max_attempts`` (the attempts are
counted in the store, so a job that kills its worker each time gives up
too); a job that gives up counts against the run's ``failure_budget`` and is
queued again; past the budget the run fails with the job's error. A phase
never closes while a job has no result.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Protocol, Sequence

import numpy as np

from scheduler.benign import benign_cache
from scheduler.evaluation import eval_jobs, eval_textures, select_final
from scheduler.iteration import MissingResults, drop_gradients, expected_frames, frame_jobs, reduce_and_step
from scheduler.options import FarmOptions
from scheduler.outputs import default_out_dir, results, write_outputs
from scheduler.state import encode_state
from undream import attacks  # lazy: make_attack loads torch when first called
from undream.lru import LRU
from undream.store import ACTIVE, UNFINISHED, NewRun

if TYPE_CHECKING:
    from undream.engine.context import RunContext
    from undream.spec.run import RunConfig
    from undream.store import BlobStore, RunSnapshot, Store

log = logging.getLogger(__name__)

PHASES = ("attack", "pre", "adversarial")
TEXTURE_VERSIONS = 8  # texture versions (run, phase, k) a process keeps read (run_batch)
# run id → the attack frames this process computed last (run_batch); plan() sends them last (below)
_SERVED: LRU[str, frozenset[int]] = LRU(64)
Contexts = Callable[[str], "RunContext"]


class Dispatch(Protocol):
    """Where stages send the next work (Celery on the farm, a queue in ``undream run``)."""

    def start(self, run_id: str) -> None:
        """Run :func:`start` for the run."""

    def frames(self, run_id: str, phase: str, k: int, batches: list[list[int]]) -> None:
        """Run :func:`run_batch` on each batch, then :func:`collect` (no batches: collect at once)."""


def batches(frames: Sequence[int], size: int) -> list[list[int]]:
    """``frames`` in as few consecutive batches of at most ``size`` as hold them, their sizes
    differing by one at most (24 frames by 9: 8, 8, 8; not 9, 9, 6), so no task is the phase's straggler."""
    frames = list(frames)
    n = -(-len(frames) // max(1, size))
    cuts = [-(-len(frames) * i // n) for i in range(n + 1)] if n else [0]  # the larger batches first
    return [frames[a:b] for a, b in zip(cuts, cuts[1:])]


def expected(run: "RunSnapshot", phase: str, k: int) -> list[int]:
    """The frame positions whose jobs ``phase`` at ``k`` needs."""
    if phase == "attack":
        return expected_frames(run, run.run_config.attack.frames_per_step, k)
    return list(range(run.n_frames))


def _current(run: "RunSnapshot", phase: str, k: int) -> bool:
    """Is the run still in ``phase`` at ``k`` (else a job or callback for it is stale)?"""
    if phase == "attack":
        return run.status == "running" and run.iteration == k
    return run.status == "evaluating" and run.iteration == k


# -- stages ---------------------------------------------------------------------------


def new_run(config: "RunConfig", n_frames: int, options: FarmOptions, *, scene_ref: str | None = None,
            out_dir: str | None = None) -> NewRun:
    """A run of ``config`` to record (:meth:`undream.store.Store.create_runs`), its id chosen."""
    return NewRun(config.name, config.to_json(), n_frames, config.seed, scene_ref=scene_ref, out_dir=out_dir,
                  farm=options.to_json())


def create(store: "Store", config: "RunConfig", n_frames: int, options: FarmOptions, *,
           scene_ref: str | None = None, out_dir: str | None = None, sweep_id: str | None = None) -> str:
    """Record a run (queued, not yet started); returns its id."""
    (run_id,) = store.create_runs([new_run(config, n_frames, options, scene_ref=scene_ref, out_dir=out_dir)],
                                  sweep_id)
    return run_id


def start(store: "Store", contexts: Contexts, run_id: str, dispatch: Dispatch) -> str:
    """The starting texture and attack state (once), then iteration 0's jobs.

    A start delivered twice (``undream resume SWEEP`` sends the start of every
    run still queued, including one whose start still waits in the broker)
    plans the run's current iteration again: the jobs' writes are idempotent
    and the step is a compare-and-set, so the run steps once; the price is the
    iteration's duplicate work. It never returns early on jobs already
    recorded: a worker killed between recording them and sending them would
    leave the run with nothing in flight.
    """
    from undream.engine.algorithm import begin, start_texture, visibility

    run = store.get_run(run_id)
    if run.status not in ACTIVE:
        return "stale"
    if run.attack_state_ref is None:
        ctx = contexts(run_id)
        T0 = start_texture(ctx)
        random = ctx.attack.config.random_start
        seen = visibility(ctx.scenes, ctx.sequence.frames, T0, ctx.config.grad_spp, ctx.config.seed) if random \
            else np.zeros(T0.shape[:2], dtype=bool)
        T_start, state = begin(ctx.attack, T0, seen, ctx.gamut)  # in the printer's gamut, when the run has one
        scalars, arrays = encode_state(state)
        store.start_run(run_id, T_start, scalars, arrays)
    store.transition(run_id, ("queued",), "running")
    run = store.get_run(run_id)
    if not _current(run, "attack", run.iteration):
        return "stale"
    plan(store, run, "attack", run.iteration, dispatch)
    return "started"


def plan(store: "Store", run: "RunSnapshot", phase: str, k: int, dispatch: Dispatch,
         only: Sequence[int] | None = None) -> list[int]:
    """Record the expected jobs of ``phase`` at ``k`` as queued and dispatch them (or ``only`` those)."""
    frames = expected(run, phase, k)
    store.queue_jobs(run.id, k, frames, phase)
    todo = frames if only is None else list(only)
    dispatch.frames(run.id, phase, k, served_last(run.id, batches(todo, FarmOptions.of(run).frames_per_task)))
    return todo


def served_last(run_id: str, parts: list[list[int]]) -> list[list[int]]:
    """``parts`` with the batches holding the most of this process's last frames of the run last.

    The process that plans an iteration is the one that closed the last: the other workers are
    already waiting, and the broker hands the batches out first come, first served, so the
    planner takes the last one. Sent last, the frames it computed before come back to it and the
    others' to them: the frames' scenes, frozen renders and transports are already in the right
    process (in the farm benchmark, a frame's first use in a process cost a second render's time
    and its transport a read). An order only: a wrong guess costs what any order did."""
    mine = _SERVED.touch(run_id) if run_id in _SERVED else frozenset()
    return sorted(parts, key=lambda batch: len(mine.intersection(batch))) if mine else parts


def run_batch(store: "Store", contexts: Contexts, run_id: str, phase: str, k: int,
              frames: Sequence[int], textures: "LRU[tuple, dict] | None" = None,
              benign: "BlobStore | None" = None) -> dict[str, Any]:
    """The header task's body: the jobs of ``frames`` that have no result yet, computed together
    (the victim once per batch of them), failures recorded.

    ``textures``: the process's cache of the textures each (run, phase, k)
    renders, so a process reads a texture version once however many of its
    batches it serves (least recently used dropped past ``TEXTURE_VERSIONS``).
    Returns a small JSON summary: frames ``done``, ``failed`` (gave up), ``retry`` (failed,
    attempts left: run the batch again), ``skipped`` (the run moved on or was
    cancelled), and the blob bytes read and written. ``benign``: the blob store that keeps benign
    evaluations (:mod:`scheduler.benign`; default the run store's) when the run's
    :attr:`FarmOptions.benign_cache` is on.
    """
    summary: dict[str, Any] = {"run_id": run_id, "phase": phase, "k": k, "done": [], "failed": [],
                               "retry": [], "skipped": []}
    run, found = store.batch_view(run_id, k, phase, frames)
    if not _current(run, phase, k):
        summary["skipped"] = list(frames)
        return summary
    max_attempts = FarmOptions.of(run).max_attempts
    jobs = {j.frame: j for j in found}
    read0, written0 = store.blobs.bytes_read, store.blobs.bytes_written
    cache: LRU[tuple, dict] = textures if textures is not None else LRU(TEXTURE_VERSIONS)
    key = (run_id, phase, k)
    todo = []
    for f in frames:
        job = jobs.get(f)
        if job is not None and job.status == "succeeded":
            summary["done"].append(f)
        elif job is not None and job.attempts >= max_attempts:  # e.g. it killed its worker each time
            why = job.error or "its worker was lost"
            store.job_failed(run_id, k, f, f"gave up after {job.attempts} attempts: {why}", phase=phase)
            summary["failed"].append(f)
        else:
            todo.append(f)
    if todo:
        try:  # the frames are computed together: a failure is every frame's failed attempt
            ctx = contexts(run_id)
            if key in cache:
                read = cache.touch(key)
            else:
                read = cache.put(key, {"k": store.texture(run_id, k)} if phase == "attack"
                                 else eval_textures(store, run_id, phase, k, ctx.attack.needs_final_loss))
            if phase == "attack":
                frame_jobs(store, ctx, run_id, k, todo, read["k"])
                _SERVED.put(run_id, frozenset(todo))
            else:
                cache = None
                if phase == "pre" and FarmOptions.of(run).benign_cache:
                    cache = benign_cache(benign or store.blobs, ctx, run.scene_ref, read["benign"])
                eval_jobs(store, ctx, run_id, phase, k, todo, read, cache)
            summary["done"].extend(todo)
        except Exception as exc:  # any failure of a job is recorded with it, then retried or counted
            error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
            for f in todo:
                job = jobs.get(f)
                again = (job.attempts if job is not None else 0) + 1 < max_attempts
                log.warning("run %s %s k=%d frame %d failed (%s): %s", run_id, phase, k, f,
                            "will retry" if again else "giving up", error)
                store.job_failed(run_id, k, f, error, will_retry=again, phase=phase)
                summary["retry" if again else "failed"].append(f)
    summary["bytes_read"] = store.blobs.bytes_read - read0
    summary["bytes_written"] = store.blobs.bytes_written - written0
    return summary


def collect(store: "Store", contexts: Contexts, run_id: str, phase: str, k: int,
            dispatch: Dispatch) -> str:
    """The callback of a phase: when every expected job has a result, close the phase.

    A job without a result is run again (never averaged away); a job that
    gave up counts against the run's failure budget and is queued again, or
    fails the run past the budget. Returns what it did: ``stale`` (the run
    moved on, was cancelled, or another callback acted), ``replanned`` (the
    run had moved on but the next phase's jobs were never recorded: a callback
    whose step committed and whose planning failed, retried; :func:`catch_up`),
    ``failed``, ``retrying``, ``rerun``, ``stepped``, ``final`` or ``done``.
    """
    run = store.get_run(run_id)
    if not _current(run, phase, k):
        return "replanned" if catch_up(store, run_id, dispatch) else "stale"
    options = FarmOptions.of(run)
    frames = expected(run, phase, k)
    jobs = {j.frame: j for j in store.jobs(run_id, k, phase)}
    failed = [f for f in frames if f in jobs and jobs[f].status == "failed"]
    missing = [f for f in frames if f not in jobs or jobs[f].status in UNFINISHED]
    if failed:
        requeued, used = store.requeue_failed(run_id, k, failed, phase)
        if used > options.failure_budget:
            msg = (f"{phase} k={k}: frame(s) {', '.join(map(str, failed))} failed "
                   f"({jobs[failed[0]].error}); failure budget of {options.failure_budget} used up")
            store.transition(run_id, ("running", "evaluating"), "failed", error=msg)
            log.error("run %s failed: %s", run_id, msg)
            return "failed"
        if requeued == 0:
            return "stale"
        log.warning("run %s %s k=%d: frame(s) %s failed; queued again (failures %d of %d)",
                    run_id, phase, k, failed, used, options.failure_budget)
        dispatch.frames(run_id, phase, k, batches(sorted(failed + missing), options.frames_per_task))
        return "retrying"
    if missing:
        log.warning("run %s %s k=%d: no result for frame(s) %s; running them again", run_id, phase, k, missing)
        dispatch.frames(run_id, phase, k, batches(missing, options.frames_per_task))
        return "rerun"
    if phase == "attack":
        return _step(store, contexts, run, k, dispatch)
    if phase == "pre":
        return _final(store, run, k, dispatch)
    return finish(store, contexts, run_id, k)


def _step(store: "Store", contexts: Contexts, run: "RunSnapshot", k: int, dispatch: Dispatch) -> str:
    # A run with a printer's gamut projects each step into it: the context holds the gamut (built once
    # per process); every worker serving the run's frames already has the context.
    gamut = contexts(run.id).gamut if run.run_config.gamut != "none" else None
    try:
        if not reduce_and_step(store, attacks.make_attack(run.run_config.attack), run.id, k, gamut):
            return "stale"
    except MissingResults:  # a job was re-queued between our look and reduce's: its callback follows
        return "stale"
    catch_up(store, run.id, dispatch)  # what a retry of this callback would do if planning fails now
    drop_gradients(store, run.id, k)  # after the next jobs are out (killed before: garbage finish() sweeps)
    return "stepped"


def _final(store: "Store", run: "RunSnapshot", k: int, dispatch: Dispatch) -> str:
    if store.has_final_texture(run.id):  # picked by another callback, or by this one before its planning failed
        return "replanned" if catch_up(store, run.id, dispatch) else "stale"
    store.put_final_texture(run.id, select_final(store, attacks.make_attack(run.run_config.attack), run.id, k))
    catch_up(store, run.id, dispatch)
    return "final"


def finish(store: "Store", contexts: Contexts, run_id: str, k: int) -> str:
    """Results into the store and the run's output folder; the run is done."""
    run = store.get_run(run_id)
    ctx = contexts(run_id)
    res = results(store, ctx, run, k)
    store.set_results(run_id, res)
    drop_gradients(store, run_id)  # any a killed callback or a late duplicate job left behind
    write_outputs(Path(run.out_dir) if run.out_dir else default_out_dir(store, run), store, ctx, run, k, res)
    return "done" if store.transition(run_id, ("evaluating",), "done") else "stale"


def current_phase(store: "Store", run: "RunSnapshot") -> str:
    """The phase a started run is in, from what the store says: ``attack`` while steps remain,
    then ``pre`` until the final texture is picked, then ``adversarial``."""
    if run.iteration < run.run_config.attack.steps:
        return "attack"
    return "adversarial" if store.has_final_texture(run.id) else "pre"


def catch_up(store: "Store", run_id: str, dispatch: Dispatch) -> bool:
    """Plan the run's current phase if none of its jobs is recorded yet; True if this call did.

    The step (or the final pick) commits before the next phase's jobs are
    recorded and sent: a callback whose planning failed after that (the
    database or the broker lost a moment) is retried, finds the run past its
    phase, and plans here what it could not. Every closing callback plans
    through this too, so the jobs are recorded once (:meth:`Store.claim_jobs`:
    only the caller that records them sends them) however many callbacks race.
    A run that finished its steps but is still ``running`` moves to ``evaluating`` first.
    """
    run = store.get_run(run_id)
    if run.status not in ("running", "evaluating") or run.attack_state_ref is None:
        return False
    if run.status == "running" and run.iteration >= run.run_config.attack.steps:
        store.transition(run_id, ("running",), "evaluating")
        run = store.get_run(run_id)
    phase = current_phase(store, run)
    frames = expected(run, phase, run.iteration)
    status = "running" if phase == "attack" else "evaluating"
    if not store.claim_jobs(run_id, run.iteration, frames, phase, (status,)):
        return False
    parts = batches(frames, FarmOptions.of(run).frames_per_task)
    dispatch.frames(run_id, phase, run.iteration, served_last(run_id, parts) if phase == "attack" else parts)
    return True


# -- control ----------------------------------------------------------------------------


def cancel(store: "Store", run_id: str) -> bool:
    """Stop a run: its queued jobs and callbacks find it cancelled and do nothing. False if it had ended."""
    return store.transition(run_id, ("queued", "running", "evaluating"), "cancelled",
                            error="cancelled by the user")


def resume_sweep(store: "Store", sweep_id: str, dispatch: Dispatch) -> tuple[list[str], list[str]]:
    """Send the start of every run of the sweep that is still queued (its start never sent, lost
    with the broker, or waiting in it: a second start is harmless, see :func:`start`), and the
    current work of every farm run of it that is running or evaluating (:func:`resume`: after a
    restarted, empty broker they have nothing in flight; a run still at work does the rest of its
    phase twice at most). Returns (the queued runs' ids, the running or evaluating runs' ids).
    Runs that ended, failed or were cancelled, and runs a process drives itself, are left alone."""
    queued = [run.id for run in store.runs(status="queued", sweep_id=sweep_id)]
    for run_id in queued:
        dispatch.start(run_id)
    active = [run.id for status in ("running", "evaluating") for run in store.runs(status=status, sweep_id=sweep_id)
              if run.owner is None]
    for run_id in active:
        resume(store, run_id, dispatch)
    return queued, active


def resume(store: "Store", run_id: str, dispatch: Dispatch, keep_attempts: bool = False) -> str:
    """Dispatch a run again from what the store says (after a crash of any part, or a cancel).

    Failed and cancelled runs are queued again with a fresh failure budget;
    the current phase's jobs without a result (and given-up ones, and attack jobs whose
    gradient blob was lost: :meth:`undream.store.Store.lost_gradients`) are
    dispatched again, then its callback. Jobs still in flight may run twice;
    every write is idempotent and the step is a compare-and-set. Returns the
    phase it dispatched (``start``, ``attack``, ``pre``, ``adversarial``) or
    ``done``. ``keep_attempts`` (the healer, :mod:`scheduler.heal`): the jobs keep the attempts
    they used, so a job that kills its worker each time still gives up at ``max_attempts``.
    """
    run = store.get_run(run_id)
    if run.status == "done":
        return "done"
    if run.status in ("failed", "cancelled"):
        store.set_status(run_id, "queued")
        store.reset_failures(run_id)
    if run.attack_state_ref is None:
        dispatch.start(run_id)
        return "start"
    store.transition(run_id, ("queued",), "running")
    run = store.get_run(run_id)
    phase = current_phase(store, run)
    if phase != "attack":
        store.transition(run_id, ("running",), "evaluating")
    run = store.get_run(run_id)
    frames = expected(run, phase, run.iteration)
    if phase == "attack":  # a gradient the machine's power cut took (written without fsync): computed again
        store.reset_jobs(run_id, run.iteration, store.lost_gradients(run_id, run.iteration), phase, succeeded=True)
    jobs = {j.frame: j for j in store.jobs(run_id, run.iteration, phase)}
    store.reset_jobs(run_id, run.iteration, [f for f in frames if f in jobs], phase, keep_attempts=keep_attempts)
    plan(store, run, phase, run.iteration, dispatch,
         only=[f for f in frames if f not in jobs or jobs[f].status != "succeeded"])
    return phase
