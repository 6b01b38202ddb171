"""The HTML pages: runs list, run page, sweep page, workers; and the run page's action buttons.

Each page renders the same plain data its ``/api`` twin returns. A page
about something still active (a queued, running or evaluating run) carries
``data-refresh``: static/dashboard.js then fetches the page again every few
seconds and swaps its live parts in place.
"""
from __future__ import annotations

from typing import Any

from flask import Blueprint, redirect, render_template, request, url_for

from undream.dashboard import fleet, framegrid, query, sweeps
from undream.dashboard.actions import act
from undream.dashboard.state import farm
from undream.store import RUN_STATUSES

EVENTS_SHOWN = 10  # a run's latest events its page shows (what the farm did by itself: heals)

pages = Blueprint("pages", __name__)
REFRESH_S = 5  # seconds between refreshes of a page about active runs


@pages.get("/")
def runs() -> Any:
    """A page of runs newest first (``?status=``, ``?sweep=``, ``?limit=``), a link to the next."""
    store, args = farm().store(), request.args
    status, sweep_id = args.get("status") or None, args.get("sweep") or None
    page = query.runs_page(store, status, sweep_id, query.check_limit(args.get("limit")), args.get("cursor"),
                           memo=farm().cache.get)
    listed = sweeps.sweeps_overview(store)
    names = {s.id: s.name for s in store.sweeps_of({r["sweep_id"] for r in page["runs"] if r["sweep_id"]})}
    return render_template(
        "runs.html", runs=page["runs"], page=page, statuses=RUN_STATUSES, status=status, sweep=sweep_id,
        sweeps=listed["sweeps"], sweeps_total=listed["total"], sweep_names=names,
        next_url=page["next"] and url_for("pages.runs", **{**args.to_dict(), "cursor": page["next"]}),
        first_url=args.get("cursor") and url_for("pages.runs", status=status, sweep=sweep_id),
        refresh=REFRESH_S if page["active"] else None)


@pages.get("/runs/<id:run_id>")
def run(run_id: str) -> Any:
    """A run's page; its frames a page at a time (``?page=N``), ``?frame=F`` shown full size."""
    store = farm().store()
    detail = query.run_detail(store, run_id)
    sweep = store.find_sweep(detail["sweep_id"]) if detail["sweep_id"] else None
    active = detail["status"] in query.ACTIVE_STATUSES
    events = store.events(detail["id"], limit=EVENTS_SHOWN)  # what the farm did to it by itself (heals)
    view = framegrid.frames_view(detail, store.get_run(detail["id"]).results,
                                 framegrid.check_number("page", request.args.get("page")),
                                 framegrid.check_number("frame", request.args.get("frame"), 0),
                                 framegrid.frame_size(store, detail["id"]) if detail["frames"] else None)
    return render_template("run.html", run=detail, grid=farm().grid(run_id), sweep=sweep, events=events, view=view,
                           version=f"{detail['updated']}-{detail['iteration']}",
                           refresh=REFRESH_S if active else None)


@pages.get("/sweeps/<id:sweep_id>")
def sweep(sweep_id: str) -> Any:
    detail = sweeps.sweep_detail(farm().store(), sweep_id, query.check_limit(request.args.get("limit") or 100),
                                 request.args.get("cursor"))
    active = any(detail["statuses"].get(s) for s in query.ACTIVE_STATUSES)
    next_url = None if detail["next"] is None else url_for("pages.sweep", sweep_id=detail["id"], cursor=detail["next"],
                                                             limit=request.args.get("limit") or None)
    return render_template("sweep.html", sweep=detail, next_url=next_url, refresh=REFRESH_S if active else None,
                           version="-".join(f"{k}{v}" for k, v in sorted(detail["statuses"].items())))


@pages.get("/workers")
def workers() -> Any:
    data = fleet.farm_overview(farm().store(), farm().settings)
    return render_template("workers.html", data=data, refresh=REFRESH_S)


@pages.post("/runs/<id:run_id>/<action>")
def action(run_id: str, action: str) -> Any:
    """The run page's buttons: the action with the form's token, then back to the run page."""
    act(farm().settings, farm().store(), run_id, action, request.form.get("token"))
    return redirect(url_for("pages.run", run_id=run_id), code=303)
