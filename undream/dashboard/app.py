"""The dashboard's Flask application: app factory, the store it reads, errors mapped at the edge.

:func:`create_app` builds one app from one :class:`~undream.settings.Settings`
(no app is built at import). The store is opened on the first request that
needs it and kept; while the database cannot be reached every page answers
503 with one line, and the app recovers by itself once it can. Failures map
to one status each (:mod:`undream.dashboard.errors`): pages get a one-line
HTML page, ``/api/`` a JSON ``{"error": ...}``; never a stack trace.
"""
from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from flask import Flask, jsonify, render_template, request
from werkzeug.exceptions import HTTPException
from werkzeug.routing import BaseConverter

from undream.dashboard import charts, filters
from undream.dashboard.api import api
from undream.dashboard.artifacts import artifacts
from undream.dashboard.errors import DashboardError, from_store_error
from undream.dashboard.markup import job_grid_html
from undream.dashboard.pages import pages
from undream.dashboard.state import EXTENSION, Farm
from undream.errors import StoreError

if TYPE_CHECKING:
    from flask import Response

    from undream.settings import Settings
    from undream.store import Store

HERE = Path(__file__).resolve().parent
UUID = r"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}"


class IdConverter(BaseConverter):
    """A run or sweep id (a UUID in lower case): nothing else reaches a view."""

    regex = UUID


def _error_response(status: int, message: str) -> "Response":
    if request.path.startswith("/api/"):
        response = jsonify({"error": message, "status": status})
    else:
        response = render_template("error.html", status=status, message=message)
    return response, status  # type: ignore[return-value]


def _register_errors(app: Flask) -> None:
    @app.errorhandler(DashboardError)
    def dashboard_error(err: DashboardError) -> Any:
        return _error_response(err.status, str(err))

    @app.errorhandler(StoreError)
    def store_error(err: StoreError) -> Any:
        mapped = from_store_error(err)
        return _error_response(mapped.status, str(mapped))

    @app.errorhandler(HTTPException)
    def http_error(err: HTTPException) -> Any:
        return _error_response(err.code or 500, f"{err.code} {err.name}: {request.path}")


def _headers(response: "Response") -> "Response":
    response.headers.setdefault("Cache-Control", "no-store")
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = "no-referrer"
    response.headers["Content-Security-Policy"] = (
        "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
        "frame-ancestors 'none'; form-action 'self'")
    return response


def create_app(settings: "Settings", opener: Callable[[str | None, str], "Store"] | None = None) -> Flask:
    """The dashboard for the farm of ``settings`` (database, blobs, broker, ``dashboard_token``).

    ``opener(database_url, blob_url)`` opens the store (default
    :func:`undream.store.open_store`, creating nothing: without a farm database every page
    is a 503 saying so until one appears).
    """
    if opener is None:
        from undream.store import open_store

        opener = functools.partial(open_store, create=False)
    app = Flask("undream.dashboard", template_folder=str(HERE / "templates"),
                static_folder=str(HERE / "static"))
    app.url_map.converters["id"] = IdConverter
    app.url_map.strict_slashes = False
    app.extensions[EXTENSION] = Farm(settings, opener)
    app.jinja_env.filters.update(filters.FILTERS)
    app.jinja_env.filters["job_grid_html"] = job_grid_html
    app.jinja_env.globals["actions_enabled"] = settings.dashboard_token is not None
    app.register_blueprint(pages)
    app.register_blueprint(api, url_prefix="/api")
    app.register_blueprint(artifacts, url_prefix="/artifacts")
    app.after_request(_headers)
    _register_errors(app)
    return app


def warm_up(app: Flask) -> None:
    """What a server does once as it starts, not during its first pages: import matplotlib and load
    its fonts (:func:`undream.dashboard.charts.warm_up`, ~0.5 s) and compile the page templates."""
    charts.warm_up()
    for name in app.jinja_env.list_templates(extensions=["html"]):
        app.jinja_env.get_template(name)


def serve(settings: "Settings", host: str, port: int, threads: int = 8) -> None:
    """Serve the dashboard with waitress (a production WSGI server) until interrupted."""
    from waitress import serve as waitress_serve

    app = create_app(settings)
    warm_up(app)
    try:
        waitress_serve(app, host=host, port=port, threads=threads, ident="undream-dashboard")
    finally:
        app.extensions[EXTENSION].close()
