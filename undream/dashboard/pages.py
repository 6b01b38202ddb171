"""The HTML pages: runs list, run page, sweep page, workers; and the run page's action buttons.

Each page renders the same plain data its ``/api`` twin returns. A page
about something still active (a queued, running or evaluating run) carries
``data-refresh``: static/dashboard.js then fetches the page again every few
seconds and swaps its live parts in place.
"""
from __future__ import annotations

from typing import Any

from flask import Blueprint, redirect, render_template, request, url_for

from undream.dashboard import fleet, query, sweeps
from undream.dashboard.actions import act
from undream.dashboard.state import farm
from undream.store import RUN_STATUSES

pages = Blueprint("pages", __name__)
REFRESH_S = 5  # seconds between refreshes of a page about active runs


@pages.get("/")
def runs() -> Any:
    store = farm().store()
    status, sweep_id = request.args.get("status") or None, request.args.get("sweep") or None
    rows = query.runs_overview(store, status, sweep_id, memo=farm().cache.get)
    all_sweeps = sweeps.sweeps_overview(store)
    active = any(r["status"] in query.ACTIVE_STATUSES for r in rows)
    return render_template("runs.html", runs=rows, statuses=RUN_STATUSES, status=status, sweep=sweep_id,
                           sweeps=all_sweeps, sweep_names={s["id"]: s["name"] for s in all_sweeps},
                           refresh=REFRESH_S if active else None)


@pages.get("/runs/<id:run_id>")
def run(run_id: str) -> Any:
    store = farm().store()
    detail = query.run_detail(store, run_id)
    sweep = store.find_sweep(detail["sweep_id"]) if detail["sweep_id"] else None
    active = detail["status"] in query.ACTIVE_STATUSES
    return render_template("run.html", run=detail, grid=farm().grid(run_id), sweep=sweep,
                           version=f"{detail['updated']}-{detail['iteration']}",
                           refresh=REFRESH_S if active else None)


@pages.get("/sweeps/<id:sweep_id>")
def sweep(sweep_id: str) -> Any:
    detail = sweeps.sweep_detail(farm().store(), sweep_id)
    active = any(detail["statuses"].get(s) for s in query.ACTIVE_STATUSES)
    return render_template("sweep.html", sweep=detail, refresh=REFRESH_S if active else None,
                           version="-".join(f"{k}{v}" for k, v in sorted(detail["statuses"].items())))


@pages.get("/workers")
def workers() -> Any:
    data = fleet.workers_overview(farm().store())
    return render_template("workers.html", data=data, refresh=REFRESH_S)


@pages.post("/runs/<id:run_id>/<action>")
def action(run_id: str, action: str) -> Any:
    """The run page's buttons: the action with the form's token, then back to the run page."""
    act(farm().settings, farm().store(), run_id, action, request.form.get("token"))
    return redirect(url_for("pages.run", run_id=run_id), code=303)
