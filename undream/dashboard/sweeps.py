"""A sweep's results table and its adversarial metric against ε per attack, as plain data."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from scheduler.query import result_rows
from undream.dashboard.errors import BadRequest
from undream.store import BadCursor

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


def sweep_detail(store: "Store", sweep_ref: str, limit: int = 100, cursor: str | None = None) -> dict[str, Any]:
    """The sweep page: name, spec, a page of results rows in grid order (grid values, status,
    headline numbers; ``next`` the cursor of the page after it), every run counted by status
    (``statuses``, ``total``) and the ε series per attack (see :func:`eps_series`)."""
    sweep = store.find_sweep(sweep_ref)
    try:
        page = store.runs_page(sweep_id=sweep.id, limit=limit, after=cursor or None, newest_first=False)
    except BadCursor as err:
        raise BadRequest(str(err)) from None
    rows = result_rows(sweep.spec, page.runs)
    for row, run in zip(rows, page.runs):
        row["run"] = run.id  # the whole id: the pages link to it
    return {"id": sweep.id, "name": sweep.name, "spec": sweep.spec, "created": sweep.created.isoformat(),
            "grid": list((sweep.spec.get("grid") or {}).keys()), "rows": rows, "next": page.next,
            "total": page.total, "statuses": store.status_counts(sweep.id), "series": eps_series(store, sweep.id)}


def sweeps_overview(store: "Store", limit: int = 50) -> dict[str, Any]:
    """The newest ``limit`` sweeps that have runs (id, name, created, their runs counted by status)
    and ``total``, how many sweeps have runs: three queries whatever the number of runs."""
    counts = store.sweep_counts()
    newest = store.sweeps_of(list(counts), limit)
    return {"sweeps": [{"id": sweep.id, "name": sweep.name, "created": sweep.created.isoformat(),
                        "runs": sum(counts[sweep.id].values()), "statuses": counts[sweep.id]}
                       for sweep in newest], "total": len(counts)}
