"""The farm's dashboard: runs, frame jobs, sweeps and workers in a browser, and a JSON API.

Flask (server-rendered Jinja pages, charts drawn by matplotlib on the
server, a little vanilla JS) served by waitress; everything is read from the
store (database and blobs) except cancel and resume, which need the
settings' ``dashboard_token``. Layers: :mod:`~undream.dashboard.query`,
:mod:`~undream.dashboard.grid`, :mod:`~undream.dashboard.sweeps` and
:mod:`~undream.dashboard.fleet` turn the store into plain data (no HTTP);
:mod:`~undream.charts` and :mod:`~undream.dashboard.images` draw
it; :mod:`~undream.dashboard.api`, :mod:`~undream.dashboard.pages` and
:mod:`~undream.dashboard.artifacts` serve it; :mod:`~undream.dashboard.app`
builds the app (:func:`create_app`) and maps errors at the edge.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from flask import Flask

    from undream.settings import Settings


def create_app(settings: "Settings", opener: Any = None) -> "Flask":
    """The dashboard's Flask app (see :func:`undream.dashboard.app.create_app`)."""
    from undream.dashboard.app import create_app as make

    return make(settings, opener)


__all__ = ["create_app"]
