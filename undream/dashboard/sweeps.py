"""A sweep's results table and its adversarial metric against ε per attack, as plain data."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from scheduler.query import result_rows

if TYPE_CHECKING:
    from undream.store import Store


def _number(value: Any) -> float | None:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    return None


def eps_series(store: "Store", sweep_id: str) -> dict[str, list[dict[str, Any]]]:
    """Attack name → points (ε in 0–255; adversarial and benign metric in [0, 1] over every frame,
    ``held_out_adversarial`` over the held-out frames or None) of the sweep's finished runs, by ε;
    runs without results are left out."""
    series: dict[str, list[dict[str, Any]]] = {}
    for run in store.runs(sweep_id=sweep_id):
        res, attack = run.results or {}, run.run_config.attack
        eps, adv = attack.eps, _number((res.get("adversarial") or {}).get("value"))
        if adv is None:
            continue
        series.setdefault(attack.name, []).append(
            {"eps": eps, "adversarial": adv, "benign": _number((res.get("benign") or {}).get("value")),
             "held_out_adversarial": _number(((res.get("held_out") or {}).get("adversarial") or {}).get("value")),
             "metric": (res.get("adversarial") or {}).get("metric"), "run_id": run.id})
    return {name: sorted(points, key=lambda p: p["eps"]) for name, points in sorted(series.items())}


def sweep_detail(store: "Store", sweep_ref: str) -> dict[str, Any]:
    """The sweep page: name, spec, one results row per run (grid values, status, headline numbers)
    and the ε series per attack (see :func:`eps_series`)."""
    sweep = store.find_sweep(sweep_ref)
    rows = result_rows(store, sweep.id, sweep.spec)
    ids = [r.id for r in store.runs(sweep_id=sweep.id)]
    for row, run_id in zip(rows, ids):
        row["run"] = run_id  # the whole id: the pages link to it
    statuses: dict[str, int] = {}
    for row in rows:
        statuses[row["status"]] = statuses.get(row["status"], 0) + 1
    return {"id": sweep.id, "name": sweep.name, "spec": sweep.spec, "created": sweep.created.isoformat(),
            "grid": list((sweep.spec.get("grid") or {}).keys()), "rows": rows, "statuses": statuses,
            "series": eps_series(store, sweep.id)}


def sweeps_overview(store: "Store") -> list[dict[str, Any]]:
    """Every sweep that has runs: id, name and its runs' statuses, newest first."""
    found: dict[str, dict[str, int]] = {}
    for run in reversed(store.runs()):
        if run.sweep_id:
            counts = found.setdefault(run.sweep_id, {})
            counts[run.status] = counts.get(run.status, 0) + 1
    out = []
    for sweep_id, counts in found.items():
        sweep = store.find_sweep(sweep_id)
        out.append({"id": sweep.id, "name": sweep.name, "created": sweep.created.isoformat(),
                    "runs": sum(counts.values()), "statuses": counts})
    return out
