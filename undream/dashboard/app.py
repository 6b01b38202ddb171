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
import ipaddress
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from flask import Flask, jsonify, render_template, request
from werkzeug.exceptions import HTTPException
from werkzeug.routing import BaseConverter

from undream import charts
from undream.dashboard import filters
from undream.dashboard.api import api
from undream.dashboard.artifacts import artifacts
from undream.dashboard.errors import BadRequest, DashboardError, from_store_error
from undream.dashboard.markup import job_grid_html
from undream.dashboard.overlay import boxes_key, boxes_svg
from undream.dashboard.pages import pages
from undream.dashboard.state import EXTENSION, Farm
from undream.errors import StoreError
from undream.redact import redact_text

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


def _redacted(response: "Response") -> "Response":
    """Every page and API answer with its URL passwords and tokens redacted (:mod:`undream.redact`):
    the store keeps the run configs as submitted, secrets included, and none of it leaves here."""
    kind = response.mimetype or ""
    if not response.direct_passthrough and (kind.startswith("text/") or kind == "application/json"):
        text = response.get_data(as_text=True)
        clean = redact_text(text)
        if clean != text:
            response.set_data(clean)
    return response


# Names a browser may use to reach the dashboard, whatever it is bound to; an IP literal is
# accepted too (DNS rebinding needs a name). Any other name must be given with --allowed-host.
LOCAL_NAMES = ("localhost", "localhost.localdomain", "127.0.0.1", "::1")


def host_allowed(host_header: str, allowed: tuple[str, ...]) -> bool:
    """Whether a request's ``Host`` header names this dashboard (see :data:`LOCAL_NAMES`)."""
    host = host_header.strip().lower()
    if host.startswith("["):
        host = host[1:].split("]", 1)[0]
    elif host.count(":") == 1:
        host = host.split(":", 1)[0]
    if host in LOCAL_NAMES or host in allowed:
        return True
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return False


def _check_host(allowed: tuple[str, ...]) -> Callable[[], Any]:
    def check() -> Any:
        if not host_allowed(request.host or "", allowed):
            return ("this dashboard does not serve the host named in the request "
                    "(start it with --allowed-host NAME to serve a name)\n", 421, {"Content-Type": "text/plain"})
        return None
    return check


def _check_query() -> None:
    """BadRequest (400) naming the parameter when a query parameter's name or value holds a control
    character: PostgreSQL refuses a NUL in a string, so ``?sweep=%00`` was a 503 "database error"."""
    for key, value in request.args.items(multi=True):
        bad = next((c for c in key + value if ord(c) < 32 or ord(c) == 127), None)
        if bad is not None:
            raise BadRequest(f"query parameter {key!r}: holds the control character {bad!r}; "
                             "ids, names, states and cursors are printable text")


def _headers(response: "Response") -> "Response":
    response = _redacted(response)
    response.headers.setdefault("Cache-Control", "no-store")
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = "no-referrer"
    response.headers["Content-Security-Policy"] = (
        "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
        "frame-ancestors 'none'; form-action 'self'")
    return response


def create_app(settings: "Settings", opener: Callable[[str | None, str], "Store"] | None = None,
               allowed_hosts: tuple[str, ...] = ()) -> Flask:
    """The dashboard for the farm of ``settings`` (database, blobs, broker, ``dashboard_token``).

    Requests whose ``Host`` is neither local, an IP address nor one of ``allowed_hosts`` are
    refused (421), so a web page cannot reach it through DNS rebinding; every answer is redacted.

    ``opener(database_url, blob_url)`` opens the store (default
    :func:`undream.store.open_store` with the settings' blob options, creating nothing: without a farm database every page
    is a 503 saying so until one appears).
    """
    if opener is None:
        from undream.store import BlobOptions, open_store

        opener = functools.partial(open_store, create=False, options=BlobOptions.of(settings))
    app = Flask("undream.dashboard", template_folder=str(HERE / "templates"),
                static_folder=str(HERE / "static"))
    app.url_map.converters["id"] = IdConverter
    app.url_map.strict_slashes = False
    app.extensions[EXTENSION] = Farm(settings, opener)
    app.jinja_env.filters.update(filters.FILTERS)
    app.jinja_env.filters["job_grid_html"] = job_grid_html
    app.jinja_env.filters["boxes_svg"] = boxes_svg
    app.jinja_env.filters["boxes_key"] = boxes_key
    app.jinja_env.globals["actions_enabled"] = settings.dashboard_token is not None
    app.register_blueprint(pages)
    app.register_blueprint(api, url_prefix="/api")
    app.register_blueprint(artifacts, url_prefix="/artifacts")
    app.before_request(_check_host(tuple(h.lower() for h in allowed_hosts)))
    app.before_request(_check_query)
    app.after_request(_headers)
    _register_errors(app)
    return app


def warm_up(app: Flask) -> None:
    """What a server does once as it starts, not during its first pages: import matplotlib and load
    its fonts (:func:`undream.charts.warm_up`, ~0.5 s) and compile the page templates."""
    charts.warm_up()
    for name in app.jinja_env.list_templates(extensions=["html"]):
        app.jinja_env.get_template(name)


def serve(settings: "Settings", host: str, port: int, threads: int = 8,
          allowed_hosts: tuple[str, ...] = ()) -> None:
    """Serve the dashboard with waitress (a production WSGI server) until interrupted."""
    from waitress import serve as waitress_serve

    app = create_app(settings, allowed_hosts=allowed_hosts + (host,))
    warm_up(app)
    try:
        waitress_serve(app, host=host, port=port, threads=threads, ident="undream-dashboard")
    finally:
        app.extensions[EXTENSION].close()
