"""The finish stage's products: results from the store, and the output folder of a run.

Outputs (the same for ``undream run`` and a submitted run): ``results.json``,
``texture_final.png`` / ``texture_final.npy`` (the 8-bit texture that was
evaluated), ``loss.png``, ``metadata.json``, ``frames_benign/`` and
``frames_adversarial/`` (PNG), and ``texture_visibility.png`` with a random
start.
"""
from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from PIL import Image

from scheduler.evaluation import prediction_from_json
from scheduler.preflight import is_scene, run_metadata
from undream import charts
from undream.color import to_uint8
from undream.errors import StoreError
from undream.metrics import classification_attack_report, detection_attack_report
from undream.redact import redact
from undream.scene.layout import frame_name
from undream.spec.io import atomic_write
from undream.versions import versions

if TYPE_CHECKING:
    from undream.engine.context import RunContext
    from undream.store import RunSnapshot, Store


def _timings(store: "Store", run_id: str, k: int) -> dict[str, float]:
    times = {"sim_render": 0.0, "victim": 0.0, "grad_render": 0.0, "reduce_step": 0.0, "evaluation": 0.0}
    for job in store.jobs(run_id, None, "attack"):
        if job.status == "succeeded":
            for key in ("sim_render", "victim", "grad_render"):
                times[key] += float(job.timings.get(key, 0.0))
    times["reduce_step"] = sum(r.step_seconds or 0.0 for r in store.iterations(run_id))
    for phase in ("pre", "adversarial"):
        times["evaluation"] += sum(float(j.timings.get("total", 0.0)) for j in store.jobs(run_id, k, phase))
    return times


def results(store: "Store", ctx: "RunContext", run: "RunSnapshot", k: int) -> dict[str, Any]:
    """The run's results from its stored predictions, iteration records and job timings."""
    from undream.engine.algorithm import judge

    task = ctx.victim.task
    pre = store.jobs(run.id, k, "pre")
    benign_preds = [prediction_from_json(task, j.result["prediction"])  # type: ignore[index]
                    for j in pre]
    adv_preds = [prediction_from_json(task, j.result["prediction"])  # type: ignore[index]
                 for j in store.jobs(run.id, k, "adversarial")]
    benign, adv = judge(ctx, benign_preds), judge(ctx, adv_preds)
    report = _success(ctx, benign_preds, adv_preds, list(range(len(benign_preds))))
    split = run.run_config.split(ctx.sequence)

    def part(positions: list[int]) -> dict[str, Any] | None:
        return None if not positions else {
            "frames": [ctx.sequence.frames[i].index for i in positions],
            "benign": _headline(judge(ctx, benign_preds, positions)),
            "adversarial": _headline(judge(ctx, adv_preds, positions)),
            "attack_success": _success(ctx, benign_preds, adv_preds, positions).to_dict()["aggregate"]}

    splits: dict[str, Any] = {"attacked": part(split.attacked), "held_out": part(split.held_out)}
    if ctx.sequence.conditions:  # a multi-condition run: conditions never attacked apart, and each condition
        held = set(run.run_config.conditions.holdout) if run.run_config.conditions else set()
        splits["held_out_conditions"] = part(split.held_out_conditions)
        splits["conditions"] = [{"name": c.name, "held_out": c.name in held, **(part(list(span)) or {})}
                                for c, span in ctx.sequence.condition_ranges()]
    iters = store.iterations(run.id)
    times = _timings(store, run.id, k)
    times["wall"] = (dt.datetime.now(dt.timezone.utc) - run.created).total_seconds()
    return {
        "run_id": run.id, "victim": ctx.config.victim, "task": task, "loss_kind": ctx.config.loss,
        **({"defence": ctx.config.defence.to_json()} if ctx.config.defence is not None else {}),
        "attack": {**ctx.attack.config.to_dict()}, "label": ctx.victim.labels[ctx.targets[0].label],
        "benign": benign, "adversarial": adv, "attack_success": report.to_dict(), **splits,
        "loss_per_iteration": [r.loss_mean for r in iters],
        **objective_terms(iters),
        "frames_dropped_per_iteration": [r.n_bad for r in iters],
        "wall_time_seconds": times,
        "benign_cache": benign_cache_record([j.result or {} for j in pre]),
    }


def objective_terms(iters: list[Any]) -> dict[str, Any]:
    """``objective_per_iteration``: each named term of the objective (``loss_victim``, ``loss_total``,
    ``reg_tv``, ...; :func:`undream.engine.algorithm.objective`) → its value per iteration, for a
    run with regularisers; nothing for a run without."""
    names = sorted({name for r in iters for name in r.terms})
    if not names:
        return {}
    return {"objective_per_iteration": {name: [r.terms.get(name) for r in iters] for name in names}}


def benign_cache_record(pre: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Where the benign evaluation came from (``pre``: its jobs' results): the cache key
    (:mod:`scheduler.benign`; a list if batches differed), the frames read from the cache and the
    frames rendered and judged by this run; None when the run did not use the cache."""
    marks = [r.get("benign_cache") for r in pre]
    if not any(marks):
        return None
    keys = sorted({m["key"] for m in marks if m})
    hits = sum(1 for m in marks if m and m.get("hit"))
    return {"key": keys[0] if len(keys) == 1 else keys, "frames_from_cache": hits, "frames_rendered": len(pre) - hits}


def _headline(judged: dict[str, Any]) -> dict[str, Any]:
    return {"metric": judged["metric"], "value": judged["value"]}


def _success(ctx: "RunContext", benign: list[Any], adversarial: list[Any], positions: list[int]) -> Any:
    """The attack-success report of the frames at ``positions``."""
    from undream.engine.algorithm import ground_truths

    label, target = ctx.targets[0].label, ctx.targets[0].target_label
    b, a = [benign[i] for i in positions], [adversarial[i] for i in positions]
    if ctx.victim.task == "classification":
        return classification_attack_report(b, a, label, target)
    truths = ground_truths(ctx)
    return detection_attack_report(b, a, [truths[i] for i in positions], label, target)


def default_out_dir(store: "Store", run: "RunSnapshot") -> Path:
    """Where a submitted run without ``--out`` writes: ``<blob folder>/outputs/<name>-<id[:8]>``; with
    blobs in the database or S3 (no shared folder), ``<cache_dir>/outputs/<name>-<id[:8]>`` on the
    machine of the worker that finishes it (:attr:`undream.store.BlobStore.local_dir`); the results
    stay in the store either way (``undream report RUN --out FOLDER``)."""
    return store.blobs.local_dir / "outputs" / f"{run.name}-{run.id[:8]}"


def write_outputs(out: Path, store: "Store", ctx: "RunContext", run: "RunSnapshot", k: int,
                  res: dict[str, Any]) -> None:
    """Write the run's output folder (see the module docstring) from the store."""
    _check_own(out, run.id)
    out.mkdir(parents=True, exist_ok=True)
    # The folder's owner first: a callback killed mid-write leaves a folder its redelivery takes as
    # this run's own (written last, a partial folder read as "a user's files" to every retry).
    meta = {"run_id": run.id, "config": redact(ctx.config.to_json()), "seed": ctx.config.seed,
            "scene_dir": str(ctx.scene_dir), "scene_blob": run.scene_ref,
            "texture_final": "8-bit quantised sRGB (texture_final.png); the same values as float in [0, 1] "
                             "(texture_final.npy) — what the adversarial evaluation rendered",
            "versions": {**versions(), "simulator": ctx.sim.name, **ctx.sim.versions()}}
    atomic_write(out / "metadata.json", json.dumps(meta, indent=1) + "\n")

    T_q = store.final_texture(run.id)
    if T_q is None:
        raise StoreError(f"run {run.id!r}: no final texture to write (the 'pre' evaluation has not finished)")
    atomic_write(out / "texture_final.png", lambda f: Image.fromarray(to_uint8(T_q)).save(f, format="PNG"))
    atomic_write(out / "texture_final.npy", lambda f: np.save(f, T_q))
    for phase, folder in (("pre", "frames_benign"), ("adversarial", "frames_adversarial")):
        (out / folder).mkdir(exist_ok=True)
        for job in store.jobs(run.id, k, phase):
            index = ctx.frame_indices[job.frame]
            image = Image.fromarray(store.blobs.get_array(job.image_ref))  # type: ignore[arg-type]
            atomic_write(out / folder / f"{frame_name('frame', index)}.png", lambda f: image.save(f, format="PNG"))
    state0 = store.attack_state(run.id, 0) or {}
    if ctx.attack.config.random_start and isinstance(state0.get("visible"), np.ndarray):
        visible = Image.fromarray(state0["visible"].astype(np.uint8) * 255)
        atomic_write(out / "texture_visibility.png", lambda f: visible.save(f, format="PNG"))
    atomic_write(out / "results.json", json.dumps(res, indent=1) + "\n")
    rows = [{"k": r.k, "loss_mean": r.loss_mean, "n_bad": r.n_bad} for r in store.iterations(run.id)]
    png = charts.loss_chart(rows, ctx.config.loss)  # the chart of the dashboard and the report
    atomic_write(out / "loss.png", png)


def _check_own(out: Path, run_id: str) -> None:
    """StoreError unless ``out`` is absent, empty, or this run's own output folder: a worker never
    writes into a scene, a user's folder or another run's outputs (the run keeps its results in the
    store, and `undream report` can write them elsewhere)."""
    if not out.is_dir() or not any(out.iterdir()):
        return
    meta = run_metadata(out)
    owner = None if meta is None else meta.get("run_id")
    if is_scene(out) or meta is None or owner not in (None, run_id):
        raise StoreError(f"output folder {out}: holds files that are not this run's outputs (a scene, a "
                         f"user's files or run {owner}'s outputs); nothing written there; the results are in "
                         f"the store: `undream report {run_id} --out FOLDER` writes them")

