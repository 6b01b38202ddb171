"""The JSON API behind every page (documented in the README, "Dashboard"); mounted at ``/api``.

Reads are GET and return the plain data of :mod:`undream.dashboard.query`,
:mod:`~undream.dashboard.grid`, :mod:`~undream.dashboard.sweeps` and
:mod:`~undream.dashboard.fleet`; the two actions are POST and need the token
(:mod:`undream.dashboard.actions`). Errors are ``{"error": "...", "status": N}``.
"""
from __future__ import annotations

from typing import Any

from flask import Blueprint, jsonify, request, url_for

from undream.dashboard import fleet, query, sweeps
from undream.dashboard.actions import TOKEN_HEADER, act
from undream.dashboard.errors import Unavailable
from undream.dashboard.state import farm

api = Blueprint("api", __name__)
API_VERSION = 1


def _links(detail: dict[str, Any]) -> dict[str, Any]:
    """URLs of the run's pictures (ids and numbers only, never paths)."""
    run_id = detail["id"]
    textures = {str(k): url_for("artifacts.texture", run_id=run_id, k=k) for k in detail["textures"]}
    if detail["final_texture"]:
        textures["final"] = url_for("artifacts.final_texture", run_id=run_id)
    frames = {view: {str(row["frame"]): url_for("artifacts.frame", run_id=run_id, view=view, frame=row["frame"])
                     for row in detail["frames"] if row[view]} for view in query.EVAL_VIEWS}
    charts = {name: url_for("artifacts.run_chart", run_id=run_id, name=name)
              for name in ("loss", "metric", "seconds")}
    return {"textures": textures, "frames": frames, "charts": charts, "page": url_for("pages.run", run_id=run_id)}


@api.get("/health")
def health() -> Any:
    """200 with the number of runs when the database answers; 503 with one line when not.

    A farm with no database yet (nothing submitted, no worker started) is healthy with no runs
    and a ``note`` saying so: the dashboard creates none, and shows it as soon as there is one.
    """
    from undream.store import NoDatabase, mask_url

    try:
        store = farm().store()
    except Unavailable as err:
        if not isinstance(err.__cause__, NoDatabase):
            raise
        return jsonify({"status": "ok", "api_version": API_VERSION, "database": None, "runs": 0,
                        "note": str(err), "actions_enabled": farm().settings.dashboard_token is not None})
    n = sum(store.status_counts().values())
    url = store.engine.url.render_as_string(hide_password=True)
    return jsonify({"status": "ok", "api_version": API_VERSION, "database": mask_url(url), "runs": n,
                    "actions_enabled": farm().settings.dashboard_token is not None})


@api.get("/runs")
def runs() -> Any:
    """A page of runs, newest first: ``?status=``, ``?sweep=``, ``?limit=`` (1–1000, default 50) and
    ``?cursor=`` (the ``next`` of the previous page); ``next`` is None on the last page."""
    args = request.args
    page = query.runs_page(farm().store(), args.get("status"), args.get("sweep"), query.check_limit(args.get("limit")),
                           args.get("cursor"), memo=farm().cache.get)
    if page["next"] is not None:
        page["next_url"] = url_for("api.runs", **{**args.to_dict(), "cursor": page["next"]})
    return jsonify(page)


@api.get("/runs/<id:run_id>")
def run(run_id: str) -> Any:
    detail = query.run_detail(farm().store(), run_id)
    attacked = query.attacked_metric(farm().attack_jobs(run_id))
    return jsonify({**detail, "attacked_metric": attacked, "links": _links(detail)})


@api.get("/runs/<id:run_id>/jobs")
def jobs(run_id: str) -> Any:
    return jsonify(farm().grid(run_id))


@api.get("/sweeps")
def sweep_list() -> Any:
    """The newest sweeps that have runs (``?limit=``, default 50), each with its runs counted by status."""
    return jsonify(sweeps.sweeps_overview(farm().store(), query.check_limit(request.args.get("limit"))))


@api.get("/sweeps/<id:sweep_id>")
def sweep(sweep_id: str) -> Any:
    """The sweep and a page of its runs in grid order (``?limit=``, ``?cursor=`` as for ``/runs``)."""
    args = request.args
    detail = sweeps.sweep_detail(farm().store(), sweep_id, query.check_limit(args.get("limit") or 100),
                                 args.get("cursor"))
    return jsonify({**detail, "links": {"chart": url_for("artifacts.sweep_chart", sweep_id=detail["id"]),
                                        "page": url_for("pages.sweep", sweep_id=detail["id"])}})


@api.get("/workers")
def workers() -> Any:
    return jsonify(fleet.farm_overview(farm().store(), farm().settings))


@api.post("/runs/<id:run_id>/<action>")
def action(run_id: str, action: str) -> Any:
    """``cancel`` or ``resume``; the token in the ``X-Undream-Token`` header or a ``token`` form field."""
    token = request.headers.get(TOKEN_HEADER) or request.form.get("token")
    return jsonify(act(farm().settings, farm().store(), run_id, action, token))
