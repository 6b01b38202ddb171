"""What ``undream status`` and ``undream results`` show, as rows of plain data (no printing here)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from scheduler.sweep import grid_values

if TYPE_CHECKING:
    from undream.store import RunSnapshot, Store


Counts = dict[tuple[str, str, int], dict[str, int]]  # (run id, phase, k) → status → jobs: Store.job_counts


def current_phase(store: "Store", run: "RunSnapshot", counts: Counts) -> tuple[str, int]:
    """The phase whose jobs the run is on (or was on when it stopped) and its k, from the run and its
    job counts (:meth:`Store.job_counts`, read once for a whole list): the attack until the last
    step, then ``pre`` until the final texture is chosen, then ``adversarial``. No query of its own;
    only a run past its last step without adversarial jobs yet costs a blob lookup."""
    k = run.iteration
    if k < run.run_config.attack.steps:
        return "attack", k
    if (run.id, "adversarial", k) in counts or store.has_final_texture(run.id):
        return "adversarial", k
    return "pre", k


def _short(text: str | None, width: int = 60) -> str:
    if not text:
        return ""
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 1] + "…"


def run_rows(store: "Store", runs: list["RunSnapshot"]) -> list[dict[str, Any]]:
    """One row per run: id, name, status, progress, failures, error. The runs' job counts are read in
    one grouped query (:meth:`Store.job_counts`), not one query per run."""
    rows = []
    counts = store.job_counts([run.id for run in runs])
    for run in runs:
        phase, k = current_phase(store, run, counts)
        jobs = counts.get((run.id, phase, k), {})
        done, total = jobs.get("succeeded", 0), sum(jobs.values())
        rows.append({"run": run.id[:8], "name": run.name, "status": run.status,
                     "iteration": f"{run.iteration}/{run.run_config.attack.steps}",
                     "phase": phase, "jobs": f"{done}/{total}" if total else "-",
                     "failures": run.failures, "updated": run.updated.strftime("%H:%M:%S"),
                     "error": _short(run.error)})
    return rows


def job_rows(store: "Store", run: "RunSnapshot") -> tuple[str, int, list[dict[str, Any]]]:
    """The per-frame jobs of the run's current phase: (phase, k, rows)."""
    phase, k = current_phase(store, run, store.job_counts([run.id]))
    rows = []
    for j in store.jobs(run.id, k, phase):
        seconds = j.timings.get("total")
        rows.append({"frame": j.frame, "status": j.status, "attempts": j.attempts,
                     "loss": "" if j.loss is None else f"{j.loss:.4f}",
                     "seconds": "" if seconds is None else f"{seconds:.3f}", "worker": j.worker or "",
                     "error": _short(j.error, 50)})
    return phase, k, rows


def result_rows(spec: dict[str, Any], runs: list["RunSnapshot"]) -> list[dict[str, Any]]:
    """One row per run of a sweep (``runs``, of the sweep whose spec is ``spec``): its grid values,
    status and headline numbers (fractions in [0, 1]: ``benign`` and ``adversarial`` over every
    frame, ``held_out_benign`` and ``held_out_adversarial`` over the frames the attack never
    rendered, None without any)."""
    rows = []
    for run in runs:
        res = run.results or {}
        success = (res.get("attack_success") or {}).get("aggregate") or {}
        held = res.get("held_out") or {}
        losses = [v for v in res.get("loss_per_iteration", []) if v is not None]
        rows.append({"run": run.id[:8], "name": run.name, **grid_values(spec, run.config),
                     "status": run.status, "metric": (res.get("benign") or {}).get("metric", ""),
                     "benign": (res.get("benign") or {}).get("value"),
                     "adversarial": (res.get("adversarial") or {}).get("value"),
                     "held_out_benign": (held.get("benign") or {}).get("value"),
                     "held_out_adversarial": (held.get("adversarial") or {}).get("value"),
                     "success_rate": success.get("success_rate"),
                     "final_loss": losses[-1] if losses else None})
    return rows
