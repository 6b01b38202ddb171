"""``undream dashboard``: serve the farm's dashboard (runs, frame jobs, sweeps, workers, JSON API).

Registered on ``undream`` by :mod:`undream.cli`. Reads the same settings as
the farm's commands (``--settings``, ``--database``, ``--blobs``; the
broker only for resume); binds 127.0.0.1 unless told otherwise.
"""
from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING, Any, Callable

import click

from undream.cli.errors import one_line_errors
from undream.cli.farm import settings_options

if TYPE_CHECKING:
    from undream.settings import Settings


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


@click.command("dashboard")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to bind (0.0.0.0 serves every interface: anyone who reaches it reads the farm).")
@click.option("--port", default=8150, show_default=True, type=click.IntRange(1, 65535), help="TCP port.")
@click.option("--threads", default=8, show_default=True, type=click.IntRange(1, 64),
              help="Request threads of the server.")
@click.option("--allowed-host", "allowed_hosts", multiple=True, metavar="NAME",
              help="A host name the dashboard answers to besides localhost and IP addresses (repeatable; "
                   "requests naming any other host are refused, against DNS rebinding).")
@settings_options
@one_line_errors
def dashboard_cmd(host: str, port: int, threads: int, allowed_hosts: tuple[str, ...],
                  settings: Callable[..., "Settings"]) -> None:
    """Serve the dashboard: runs, frame jobs, sweeps and workers, read from the store (read-only
    except cancel and resume, which need dashboard_token)."""
    from undream.dashboard.app import serve
    from undream.store import mask_url

    cfg = settings()
    database = mask_url(cfg.database_url) if cfg.database_url else f"SQLite in {cfg.blob_url}"
    click.echo(f"undream dashboard: http://{host}:{port}/ (database {database}; actions "
               f"{'need the dashboard token' if cfg.dashboard_token else 'off: no dashboard_token'})")
    if not _loopback(host):
        click.echo(f"undream dashboard: warning: bound to {host}, not loopback: anyone who reaches it "
                   "reads the farm", err=True)
    serve(cfg, host, port, threads, allowed_hosts)


COMMANDS: tuple[Any, ...] = (dashboard_cmd,)
