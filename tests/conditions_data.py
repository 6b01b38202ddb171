"""A finished multi-condition run built through the Store API, for the report's and the dashboard's
page tests: no rendering, no victim, a second or two for 384 frames.

:func:`conditions_output` writes what ``undream report FOLDER`` reads of an `undream run` output
folder (``metadata.json`` naming the run, ``store/``): a classifier run over ``conditions`` ×
``views`` frames of ``px`` pixels, the last conditions held out whole and every fourth view held out
within the others; the adversarial texture fools condition ``c`` on about ``c / conditions`` of
its frames, so the conditions differ in weakness.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dashboard_data import LABELS, TRUE_LABEL, WORKERS, RunShape, _frame, add_run


def condition_names(n: int) -> list[str]:
    times, weather = ("dawn", "noon", "dusk", "night"), ("clear", "cloudy", "rain", "fog")
    return [f"{times[i % 4]}-{weather[(i // 4) % 4]}" + (f"-{i // 16}" if i >= 16 else "") for i in range(n)]


def _fooled(c: int, v: int, conditions: int, views: int) -> bool:
    """Whether the adversarial texture fools the victim on view ``v`` of condition ``c``."""
    return (v * 7 + c * 3) % views < round(views * (c + 1) / (conditions + 1))


def _rows(preds: list[int]) -> list[dict[str, Any]]:
    return [{"frame": f, "prediction": p, "class": LABELS[p], "score": 0.6 + 0.3 * ((f * 13) % 10) / 10,
             "correct": p == TRUE_LABEL} for f, p in enumerate(preds)]


def _block(frames: list[int], benign: list[int], adv: list[int]) -> dict[str, Any]:
    acc = lambda preds: float(np.mean([preds[f] == TRUE_LABEL for f in frames]))  # noqa: E731
    eligible = [f for f in frames if benign[f] == TRUE_LABEL]
    fooled = [f for f in eligible if adv[f] != TRUE_LABEL]
    return {"frames": frames, "benign": {"metric": "accuracy", "value": acc(benign)},
            "adversarial": {"metric": "accuracy", "value": acc(adv)},
            "attack_success": {"success_rate": len(fooled) / len(eligible) if eligible else None,
                               "n_success": len(fooled), "n_eligible": len(eligible)}}


def conditions_results(conditions: int, views: int, held: int) -> tuple[dict[str, Any], list[int], list[int]]:
    """results.json of the run (frame index = position), and the benign and adversarial predictions."""
    n = conditions * views
    benign = [TRUE_LABEL if (f * 5) % 17 else (TRUE_LABEL + 2) % len(LABELS) for f in range(n)]
    adv = [(TRUE_LABEL + 1 + f % 2) % len(LABELS) if _fooled(f // views, f % views, conditions, views)
           else benign[f] for f in range(n)]
    names = condition_names(conditions)
    held_names = set(names[conditions - held:])
    spans = {name: list(range(c * views, (c + 1) * views)) for c, name in enumerate(names)}
    attacked = [f for name in names if name not in held_names for f in spans[name] if (f % views) % 4 != 3]
    held_views = [f for name in names if name not in held_names for f in spans[name] if (f % views) % 4 == 3]
    held_conds = [f for name in names if name in held_names for f in spans[name]]
    everything = _block(list(range(n)), benign, adv)
    results = {
        "task": "classification", "victim": "bundled:classifier", "label": LABELS[TRUE_LABEL],
        "attack": {"name": "pgd", "eps": 32.0, "steps": 2},
        "benign": {"metric": "accuracy", "value": everything["benign"]["value"], "per_frame": _rows(benign)},
        "adversarial": {"metric": "accuracy", "value": everything["adversarial"]["value"], "per_frame": _rows(adv)},
        "attack_success": {"aggregate": everything["attack_success"]},
        "attacked": _block(attacked, benign, adv), "held_out": _block(held_views, benign, adv),
        "held_out_conditions": _block(held_conds, benign, adv) if held_conds else None,
        "conditions": [{"name": name, "held_out": name in held_names, **_block(spans[name], benign, adv)}
                       for name in names],
        "loss_per_iteration": [0.5, 1.5], "wall_time_seconds": {"wall": 12.5},
    }
    return results, benign, adv


def conditions_output(folder: Path, conditions: int = 16, views: int = 24, px: int = 64, held: int = 4,
                      seed: int = 0) -> dict[str, Any]:
    """Write the output folder (see the module docstring); returns {"run_id", "results"}."""
    from undream.store import open_store

    n = conditions * views
    results, _, adv = conditions_results(conditions, views, held)
    store = open_store(None, Path(folder) / "store")
    try:
        shape = RunShape("bin-16-conditions", "evaluating", frames=n, steps=2, done_steps=2, frame_px=px)
        run_id = add_run(store, shape, np.random.default_rng(seed))  # iterations, the benign evaluation
        final = store.final_texture(run_id)
        store.queue_jobs(run_id, 2, range(n), "adversarial")
        for f in range(n):
            store.job_started(run_id, 2, f, "adversarial", worker=WORKERS[f % len(WORKERS)])
            store.eval_succeeded(run_id, 2, f, "adversarial", {"prediction": {"label": adv[f], "score": 0.8}},
                                 _frame(final, px), {"total": 0.3})
        store.set_results(run_id, results)
        store.set_status(run_id, "done")
    finally:
        store.close()
    (Path(folder) / "metadata.json").write_text(json.dumps({"run_id": run_id, "config": {}}) + "\n")
    (Path(folder) / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    return {"run_id": run_id, "results": results}
