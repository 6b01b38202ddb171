"""A run's frame × iteration grid of job states, as plain data (no HTTP here).

Rows are frame positions, columns the attack iterations 0 … k and then the
two evaluation phases (``pre``: benign, ``adversarial``). Each cell is one
frame job: its status, seconds (``timings.total``), attempts, worker and
error. A succeeded job is *slow* when it took more than
:data:`~undream.dashboard.query.SLOW_FACTOR` times the median of the run's
succeeded attack jobs.
"""
from __future__ import annotations

import statistics
from typing import TYPE_CHECKING, Any

from undream.dashboard.query import SLOW_FACTOR

if TYPE_CHECKING:
    from undream.store import JobLine, JobSnapshot, Store

ERROR_CHARS = 300  # an error is cut to this many characters in a cell


def _seconds(job: "JobLine | JobSnapshot") -> float | None:
    total = job.timings.get("total")
    return float(total) if isinstance(total, (int, float)) and not isinstance(total, bool) else None


def _cell(job: "JobLine | JobSnapshot", slow_after: float | None) -> dict[str, Any]:
    seconds = _seconds(job)
    error = " ".join((job.error or "").split())
    return {"status": job.status, "seconds": seconds, "attempts": job.attempts, "worker": job.worker,
            "error": error[:ERROR_CHARS] or None,
            "slow": bool(slow_after is not None and seconds is not None and job.status == "succeeded"
                         and seconds > slow_after)}


def job_grid(store: "Store", run_id: str, attack_jobs: list["JobLine"] | None = None) -> dict[str, Any]:
    """The grid: ``columns`` (labels), ``rows`` (one list of cells or None per frame), the median job time.

    ``attack_jobs``: the run's attack jobs when the caller already read them.
    """
    run = store.get_run(run_id)
    attack = store.job_lines(run_id) if attack_jobs is None else attack_jobs
    evals = [store.jobs(run_id, run.iteration, phase) for phase in ("pre", "adversarial")]
    times = [s for j in attack if j.status == "succeeded" and (s := _seconds(j)) is not None]
    median = statistics.median(times) if times else None
    slow_after = None if median is None else SLOW_FACTOR * median
    n_iter = max((j.k + 1 for j in attack), default=0)
    columns = [str(k) for k in range(n_iter)]
    grid: list[list[dict[str, Any] | None]] = [[None] * n_iter for _ in range(run.n_frames)]
    for job in attack:
        grid[job.frame][job.k] = _cell(job, slow_after)
    if any(evals):
        columns += ["benign", "adversarial"]
        for row in grid:
            row.extend([None, None])
        for i, jobs in enumerate(evals):
            for job in jobs:
                grid[job.frame][n_iter + i] = _cell(job, None)
    counts: dict[str, int] = {}
    for job in attack:
        counts[job.status] = counts.get(job.status, 0) + 1
    return {"run_id": run_id, "columns": columns, "n_iterations": n_iter, "rows": grid,
            "median_seconds": median, "slow_after_seconds": slow_after, "counts": counts,
            "slow": sum(c["slow"] for row in grid for c in row if c)}
