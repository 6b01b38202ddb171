"""A sweep's runs side by side: per metric and per cell of the grid, the values of the cell's seeds.

A *cell* is one combination of the grid's values other than the seed axes
(:data:`SEED_AXES`, whose values are repeats): its *series* (the attack and
every other value but x) and its *x* (ε when the grid varies ``attack.eps``,
else the grid's last other axis). A cell's values are its finished runs'
(one per seed); runs not finished (running, failed, ...) are counted, not
shown. Metrics (:data:`METRICS`) are fractions in [0, 1]: the adversarial
accuracy or AP@0.5 of a split, and the attack success (fooled of the frames
the victim got right before the attack) over every frame. No drawing here.
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping

from scheduler.sweep import grid_values

if TYPE_CHECKING:
    from undream.store import RunSnapshot, SweepSnapshot

SEED_AXES = ("seed", "attack.seed")  # grid fields whose values are repeats: spread, not cells
X_FIRST = "attack.eps"  # the x axis whenever the grid varies it
METRICS = {  # key → what a chart and the table call it (the victim's metric is named apart)
    "attacked": "adversarial {m}, attacked frames",
    "held_out": "adversarial {m}, held-out views",
    "held_out_conditions": "adversarial {m}, held-out conditions",
    "success": "attack success, all frames",
}
SPLIT_OF = {"attacked": "attacked", "held_out": "held_out", "held_out_conditions": "held_out_conditions"}


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def metric_value(results: Mapping[str, Any], metric: str, side: str = "adversarial") -> float | None:
    """``metric`` of :data:`METRICS` read from results.json (``side``: benign or adversarial value of
    a split; the success rate has no sides); None when the run has no such number."""
    if metric == "success":
        return None if side != "adversarial" else _number(
            ((results.get("attack_success") or {}).get("aggregate") or {}).get("success_rate"))
    block = results.get(SPLIT_OF[metric]) or {}
    return _number((block.get(side) or {}).get("value"))


@dataclass(frozen=True)
class Cell:
    """One cell of one metric: its series and x, the finished seeds' values and its runs' count."""

    series: str
    x: Any
    metric: str
    values: tuple[float, ...]  # one per finished run, fractions in [0, 1]
    runs: int  # the cell's runs in the sweep, finished or not

    @property
    def mean(self) -> float | None:
        return statistics.fmean(self.values) if self.values else None

    @property
    def std(self) -> float | None:
        """Sample standard deviation over seeds; None with fewer than two."""
        return statistics.stdev(self.values) if len(self.values) > 1 else None


@dataclass(frozen=True)
class Comparison:
    """The sweep's cells per metric (grid order), its axes and how many of its runs finished."""

    x_axis: str | None  # the grid field along x; None when the grid varies seeds only
    series_axes: tuple[str, ...]
    seed_axes: tuple[str, ...]
    metric: str | None  # the victim's metric of every finished run (accuracy, ap50), None when mixed
    cells: dict[str, list[Cell]]  # metric → cells with at least one value (metrics without any: absent)
    benign: dict[str, float] = field(default_factory=dict)  # metric → mean benign value over finished runs
    statuses: dict[str, int] = field(default_factory=dict)  # run status → runs

    @property
    def finished(self) -> int:
        return self.statuses.get("done", 0)

    @property
    def total(self) -> int:
        return sum(self.statuses.values())

    @property
    def metric_name(self) -> str:
        return {"accuracy": "accuracy", "ap50": "AP@0.5"}.get(self.metric or "", "value")

    def title(self, metric: str) -> str:
        return METRICS[metric].format(m=self.metric_name)


def _axes(grid: list[str]) -> tuple[str | None, tuple[str, ...], tuple[str, ...]]:
    """(x axis, series axes, seed axes) of the grid's fields."""
    seeds = tuple(k for k in grid if k in SEED_AXES)
    others = [k for k in grid if k not in SEED_AXES]
    if not others:
        return None, (), seeds
    x = X_FIRST if X_FIRST in others else next((k for k in reversed(others) if k != "attack.name"), others[-1])
    return x, tuple(k for k in others if k != x), seeds


def _series(run: "RunSnapshot", axes: tuple[str, ...], values: Mapping[str, Any]) -> str:
    """The series' label: the attack's name, then every other series axis as field=value."""
    parts = [str(values["attack.name"]) if "attack.name" in axes else run.run_config.attack.name]
    return ", ".join(parts + [f"{k}={values[k]}" for k in axes if k != "attack.name"])


def compare(sweep: "SweepSnapshot", runs: list["RunSnapshot"]) -> Comparison:
    """The sweep's runs as cells (see the module docstring); ``runs`` in the sweep's (grid) order."""
    grid = [str(k) for k in sweep.spec.get("grid") or {}]
    x_axis, series_axes, seeds = _axes(grid)
    found: dict[tuple[str, Any], dict[str, list[float]]] = {}
    counts: dict[tuple[str, Any], int] = {}
    benign: dict[str, list[float]] = {}
    statuses: dict[str, int] = {}
    metrics = set()
    for run in runs:
        values = grid_values(sweep.spec, run.config)
        key = (_series(run, series_axes, values), values[x_axis] if x_axis else "all")
        counts[key] = counts.get(key, 0) + 1
        found.setdefault(key, {})
        statuses[run.status] = statuses.get(run.status, 0) + 1
        if run.status != "done" or not run.results:
            continue
        metrics.add((run.results.get("benign") or {}).get("metric"))
        for metric in METRICS:
            value = metric_value(run.results, metric)
            if value is not None:
                found[key].setdefault(metric, []).append(value)
            start = metric_value(run.results, metric, "benign")
            if start is not None:
                benign.setdefault(metric, []).append(start)
    keys = _ordered(list(found))
    cells = {m: [Cell(s, x, m, tuple(found[(s, x)].get(m, ())), counts[(s, x)]) for s, x in keys]
             for m in METRICS if any(found[k].get(m) for k in keys)}
    return Comparison(x_axis, series_axes, seeds, metrics.pop() if len(metrics) == 1 else None, cells,
                      {m: statistics.fmean(v) for m, v in benign.items()}, statuses)


def _ordered(keys: list[tuple[str, Any]]) -> list[tuple[str, Any]]:
    """Cells by series (first seen first), then x: by value when every x is a number, else as seen."""
    series = list(dict.fromkeys(s for s, _ in keys))
    numeric = all(_number(x) is not None for _, x in keys)
    return sorted(keys, key=lambda k: (series.index(k[0]), float(k[1]) if numeric else keys.index(k)))


def numeric_x(comparison: Comparison) -> bool:
    """Whether every cell's x is a number (drawn to scale; otherwise one tick per value)."""
    return all(_number(c.x) is not None for cells in comparison.cells.values() for c in cells)


def cell_rows(comparison: Comparison) -> list[dict[str, Any]]:
    """Every cell of every metric as a CSV row: series, x, metric, seeds finished of runs, mean, sample
    standard deviation, min, max and the values themselves (fractions in [0, 1])."""
    return [{"series": c.series, "x_axis": comparison.x_axis or "", "x": c.x, "metric": c.metric,
             "n_seeds": len(c.values), "n_runs": c.runs, "mean": c.mean, "std": c.std,
             "min": min(c.values) if c.values else None, "max": max(c.values) if c.values else None,
             "values": " ".join(f"{v:.6g}" for v in c.values)}
            for cells in comparison.cells.values() for c in cells]
