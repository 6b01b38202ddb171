"""What the dashboard shows, as plain JSON-ready data read through the store (no HTTP here).

Every function takes the :class:`~undream.store.Store` and returns dicts of
strings, numbers, lists and None; the pages render them and the JSON API
returns them as they are. Times are ISO 8601 UTC strings, durations seconds,
losses the run's loss (its ``loss`` config: ``ce`` in nats, ...), metric
values fractions in [0, 1] (accuracy, or AP at IoU 0.5), ε in 0–255 sRGB
units. A missing run or sweep raises the store's ``StoreError`` (mapped at
the edge by :func:`undream.dashboard.errors.from_store_error`).
"""
from __future__ import annotations

import datetime as dt
import functools
import statistics
from typing import TYPE_CHECKING, Any, Callable, Sequence

from scheduler.query import current_phase
from undream.dashboard.errors import BadRequest
from undream.runlist import ACTIVE_STATUSES, MAX_PAGE
from undream.store import RUN_STATUSES, BadCursor

if TYPE_CHECKING:
    from undream.store import IterationSnapshot, JobLine, JobSnapshot, RunSnapshot, Store

Memo = Callable[[tuple[Any, ...], Callable[[], Any]], Any]  # cache.get(key, make)
EVAL_VIEWS = {"benign": "pre", "adversarial": "adversarial"}  # URL name → job phase
SLOW_FACTOR = 2.0  # a job this many times the run's median job time is slow
MAX_BOXES = 5  # a detector's boxes drawn on a frame (the highest-scoring; results.json keeps as many)
PAGE = 50  # runs in a page of the runs list unless the request asks for another ``limit``


def iso(stamp: dt.datetime | None) -> str | None:
    return None if stamp is None else stamp.isoformat()


def check_status(status: str | None) -> str | None:
    if status not in (None, "", *RUN_STATUSES):
        raise BadRequest(f"status {status!r}: not a run status; valid statuses are {', '.join(RUN_STATUSES)}")
    return status or None


def _frames_per_iteration(run: "RunSnapshot", phase: str) -> int:
    per_step = run.run_config.attack.frames_per_step
    if phase == "attack" and per_step is not None and per_step < run.n_frames:
        return per_step
    return run.n_frames


def _eta(run: "RunSnapshot", iters: list["IterationSnapshot"], now: dt.datetime) -> float | None:
    """Seconds until the last attack step at the median pace of the steps so far; None when unknown."""
    steps = run.run_config.attack.steps
    if run.status != "running" or not iters or run.iteration >= steps:
        return None
    stamps = [run.created] + [r.created for r in iters]
    pace = statistics.median((b - a).total_seconds() for a, b in zip(stamps, stamps[1:]))
    since_last = (now - stamps[-1]).total_seconds()
    return max(0.0, pace * (steps - run.iteration) - since_last)


class ListReads:
    """The iteration records and job counts of a list page's runs, each read in one query when
    first needed (instead of two queries per run)."""

    def __init__(self, store: "Store", run_ids: list[str]) -> None:
        self._store, self._ids = store, run_ids

    @functools.cached_property
    def iterations(self) -> dict[str, list["IterationSnapshot"]]:
        return self._store.iterations_of(self._ids)

    @functools.cached_property
    def counts(self) -> dict[tuple[str, str, int], dict[str, int]]:
        return self._store.job_counts(self._ids)


def run_summary(store: "Store", run: "RunSnapshot", now: dt.datetime,
                reads: ListReads | None = None) -> dict[str, Any]:
    """One row of the runs list: state, progress, losses (for the sparkline), age and ETA.

    ``reads``: the list page's bulk reads (default: this run's alone).
    """
    reads = reads or ListReads(store, [run.id])
    phase, k = current_phase(store, run, reads.counts)
    done = reads.counts.get((run.id, phase, k), {}).get("succeeded", 0) if run.status != "done" else 0
    iters = reads.iterations.get(run.id, [])
    config = run.run_config
    evaluation = _evaluation(run)
    return {
        "id": run.id, "name": run.name, "status": run.status, "sweep_id": run.sweep_id,
        "victim": config.victim, "loss_kind": config.loss,
        "attack": config.attack.name, "eps": config.attack.eps,
        "iteration": run.iteration, "steps": config.attack.steps, "n_frames": run.n_frames, "phase": phase,
        "frames_done": done, "frames_total":
            _frames_per_iteration(run, phase) if run.status != "done" else run.n_frames,
        "loss": [r.loss_mean for r in iters], "created": iso(run.created), "updated": iso(run.updated),
        "age_s": (now - run.created).total_seconds(), "eta_s": _eta(run, iters, now),
        "failures": run.failures, "error": run.error,
        "metric": evaluation["metric"], "benign": evaluation["benign"],
        "adversarial": evaluation["adversarial"],
        "held_out_benign": (evaluation["held_out"] or {}).get("benign"),
        "held_out_adversarial": (evaluation["held_out"] or {}).get("adversarial"),
        "owner": getattr(run, "owner", None), "heartbeat": iso(getattr(run, "heartbeat", None)),
    }


def check_limit(limit: str | int | None) -> int:
    """The page size a request asks for (default :data:`PAGE`), or BadRequest naming the bad value."""
    if limit in (None, ""):
        return PAGE
    try:
        value = int(limit)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        value = 0
    if not 1 <= value <= MAX_PAGE:
        raise BadRequest(f"limit {limit!r}: must be a whole number from 1 to {MAX_PAGE}")
    return value


def runs_page(store: "Store", status: str | None = None, sweep_id: str | None = None,
              limit: int = PAGE, cursor: str | None = None, now: dt.datetime | None = None,
              memo: Memo | None = None) -> dict[str, Any]:
    """A page of the runs list (with ``status``, of sweep ``sweep_id``), newest first, after
    ``cursor``: ``runs`` (:func:`run_summary` rows), ``next`` (the cursor of the next page, None on
    the last), ``total`` (runs matching the filters), ``counts`` (runs per status, of the sweep or
    of the farm) and ``active`` (queued, running or evaluating runs matching the filters). A fixed
    number of queries whatever the farm's size: the page, its count, the tally, and the page's
    iteration records and job counts.

    ``memo(key, make)``: a cache for the rows of finished runs (their jobs and iterations no longer
    change; the key holds the run's ``updated`` time, which a resume changes); ages are made fresh.
    """
    now = now or dt.datetime.now(dt.timezone.utc)
    status = check_status(status)
    try:
        page = store.runs_page(status, sweep_id or None, limit, cursor or None)
    except BadCursor as err:
        raise BadRequest(str(err)) from None
    reads = ListReads(store, [run.id for run in page.runs])
    rows = []
    for run in page.runs:
        if memo is None or run.status in ACTIVE_STATUSES:
            rows.append(run_summary(store, run, now, reads))
            continue
        row = memo(("summary", run.id, run.updated, run.status),
                   lambda run=run: run_summary(store, run, now, reads))
        rows.append({**row, "age_s": (now - run.created).total_seconds()})
    counts = store.status_counts(sweep_id or None)
    active = sum(n for s, n in counts.items() if s in ACTIVE_STATUSES and status in (None, s))
    return {"runs": rows, "next": page.next, "total": page.total, "counts": counts, "active": active,
            "limit": limit}


def _split(res: dict[str, Any], name: str) -> dict[str, Any] | None:
    """results.json's ``attacked`` or ``held_out`` block as ``frames`` (how many), ``benign``,
    ``adversarial`` and ``success_rate`` (fractions); None when the run has no such frames."""
    block = res.get(name)
    if not isinstance(block, dict):
        return None
    return {"frames": len(block.get("frames") or []), "benign": (block.get("benign") or {}).get("value"),
            "adversarial": (block.get("adversarial") or {}).get("value"),
            "success_rate": (block.get("attack_success") or {}).get("success_rate")}


def _evaluation(run: "RunSnapshot") -> dict[str, Any]:
    """The evaluation's headline numbers (every frame at ``eval_spp``) and its ``attacked`` /
    ``held_out`` / ``held_out_conditions`` splits (see :func:`_split`)."""
    res = run.results or {}
    benign, adv = res.get("benign") or {}, res.get("adversarial") or {}
    success = ((res.get("attack_success") or {}).get("aggregate") or {}).get("success_rate")
    return {"metric": benign.get("metric"), "benign": benign.get("value"),
            "adversarial": adv.get("value"), "success_rate": success, "label": res.get("label"),
            "attacked": _split(res, "attacked"), "held_out": _split(res, "held_out"),
            "held_out_conditions": _split(res, "held_out_conditions")}


def _verdict(job: "JobLine | JobSnapshot") -> bool | None:
    """Whether an attack job's frame still fooled nobody: classified correctly or detected; None unknown."""
    pred = (job.result or {}).get("prediction") if job.status == "succeeded" else None
    if not isinstance(pred, dict):
        return None
    ok = pred.get("correct", pred.get("detected"))
    return ok if isinstance(ok, bool) else None


def attacked_metric(jobs: "Sequence[JobLine | JobSnapshot]") -> list[dict[str, Any]]:
    """Per attack iteration ``k``: ``value``, the fraction (0–1) of the attacked frames rendered with
    texture ``k`` (the simulator at ``sim_spp``) that the victim still classifies correctly, or
    detects; ``n``, how many frames had a prediction. Iterations without one are left out."""
    by_k: dict[int, list[bool]] = {}
    for job in jobs:
        ok = _verdict(job)
        if ok is not None:
            by_k.setdefault(job.k, []).append(ok)
    return [{"k": k, "value": sum(v) / len(v), "n": len(v)} for k, v in sorted(by_k.items())]


def _iteration_rows(run: "RunSnapshot", iters: list["IterationSnapshot"]) -> list[dict[str, Any]]:
    stamps = [run.created] + [r.created for r in iters]
    return [{"k": r.k, "loss_mean": r.loss_mean, "n_ok": r.n_ok, "n_bad": r.n_bad,
             "dropped_frames": r.dropped_frames, "grad_norm": r.grad_norm, "step_seconds": r.step_seconds,
             "seconds": (stamps[i + 1] - stamps[i]).total_seconds(), "finished": iso(r.created),
             **({"terms": r.terms} if r.terms else {})}  # the objective's named terms, with regularisers
            for i, r in enumerate(iters)]


def texture_versions(run: "RunSnapshot", most: int = 8) -> list[int]:
    """The iterations whose textures the strip shows: 0, the latest, and evenly between (at most ``most``)."""
    last = run.iteration
    if last + 1 <= most:
        return list(range(last + 1))
    return sorted({round(i * last / (most - 1)) for i in range(most)})


def _prediction(job: "JobSnapshot | None", names: dict[int, str]) -> dict[str, Any] | None:
    """An evaluation job's prediction: class id, name (when the results give it) and score, or boxes."""
    if job is None or job.status != "succeeded" or not job.result:
        return None
    pred = dict(job.result.get("prediction") or {})
    if "label" in pred:
        pred["name"] = names.get(int(pred["label"]))
    return pred


def _class_names(run: "RunSnapshot") -> dict[int, str]:
    """Class id → name, from the per-frame rows of the results (the store keeps ids only)."""
    names: dict[int, str] = {}
    for side in ("benign", "adversarial"):
        for row in ((run.results or {}).get(side) or {}).get("per_frame") or []:
            if "prediction" in row and "class" in row:
                names[int(row["prediction"])] = str(row["class"])
    return names


def _top_boxes(pred: dict[str, Any]) -> list[dict[str, Any]]:
    """The :data:`MAX_BOXES` highest-scoring of a stored prediction's raw ``boxes``/``scores``, as
    results.json's ``boxes`` rows with no class name (``label`` None: the store keeps class ids only)."""
    dets = [{"box": [round(float(v), 1) for v in b], "score": round(float(s), 4), "label": None}
            for b, s in zip(pred.get("boxes") or [], pred.get("scores") or [])]
    return sorted(dets, key=lambda d: -d["score"])[:MAX_BOXES]


def _with_boxes(store: "Store", run: "RunSnapshot", job: "JobSnapshot", pred: dict[str, Any],
                row: dict[str, Any] | None) -> dict[str, Any]:
    """A detector's evaluation prediction with what the run page draws: ``detections`` (at most
    :data:`MAX_BOXES`, ``{box, score, label}``, frame pixels), ``truth_box``, ``truth_label``,
    ``detected`` and ``size`` (the frame's width and height, px). Job rows written before they kept
    these are filled from the results.json per-frame ``row`` when there is one, else from the raw
    boxes (no class names, no true box), the size from the frame itself."""
    if "detections" in pred and "size" in pred:
        return pred
    row = row or {}
    pred["detections"] = row["boxes"] if isinstance(row.get("boxes"), list) else _top_boxes(pred)
    pred["truth_box"] = row.get("truth_box")
    pred["truth_label"] = (run.results or {}).get("label")
    if isinstance(row.get("detected"), bool):
        pred["detected"] = row["detected"]
    if job.image_ref:
        h, w = store.blobs.get_array(job.image_ref).shape[:2]
        pred["size"] = [int(w), int(h)]
    return pred


def _per_frame(run: "RunSnapshot", view: str) -> list[dict[str, Any]]:
    """results.json's per-frame rows of ``view`` in frame-position order (empty when they do not
    cover every frame)."""
    rows = ((run.results or {}).get(view) or {}).get("per_frame") or []
    return rows if len(rows) == run.n_frames else []


def eval_frames(store: "Store", run: "RunSnapshot") -> list[dict[str, Any]]:
    """Per frame: the benign and adversarial predictions and whether each frame image exists; a
    detector's with its boxes (:func:`_with_boxes`)."""
    names = _class_names(run)
    label = (run.results or {}).get("label")
    views = {view: {j.frame: j for j in store.jobs(run.id, run.iteration, phase)}
             for view, phase in EVAL_VIEWS.items()}
    per_frame = {view: _per_frame(run, view) for view in EVAL_VIEWS}
    rows = []
    for f in range(run.n_frames):
        row: dict[str, Any] = {"frame": f}
        for view, jobs in views.items():
            pred = _prediction(jobs.get(f), names)
            if pred is not None and label is not None and pred.get("name") is not None:
                pred["correct"] = pred["name"] == label
            if pred is not None and "boxes" in pred:
                pred = _with_boxes(store, run, jobs[f], pred, per_frame[view][f] if per_frame[view] else None)
            row[view] = pred
        if row["benign"] or row["adversarial"]:
            rows.append(row)
    return rows


def chart_data(store: "Store", run_id: str, attack_jobs: list["JobLine"] | None = None) -> dict[str, Any]:
    """What the run's charts need: iteration rows, the evaluation, the loss kind, the steps, the
    samples per pixel of the attack's and the evaluation's renders, and ``attacked``
    (:func:`attacked_metric` of ``attack_jobs``, read from the store when not given)."""
    run = store.get_run(run_id)
    jobs = store.job_lines(run_id) if attack_jobs is None else attack_jobs
    return {"iterations": _iteration_rows(run, store.iterations(run_id)), "evaluation": _evaluation(run),
            "loss_kind": run.run_config.loss, "steps": run.run_config.attack.steps,
            "attacked": attacked_metric(jobs), "sim_spp": run.run_config.sim_spp, "eval_spp": run.run_config.eval_spp}


def run_detail(store: "Store", run_id: str, now: dt.datetime | None = None) -> dict[str, Any]:
    """The run page: its summary, iteration records, evaluation, frames, texture versions and config."""
    now = now or dt.datetime.now(dt.timezone.utc)
    run = store.get_run(run_id)
    return {**run_summary(store, run, now), "seed": run.seed, "config": run.config,
            "farm": run.farm, "out_dir": run.out_dir,
            "iterations": _iteration_rows(run, store.iterations(run_id)),
            "evaluation": _evaluation(run), "frames": eval_frames(store, run),
            "textures": texture_versions(run), "final_texture": store.final_texture(run_id) is not None}
