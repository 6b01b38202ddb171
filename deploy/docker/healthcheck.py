#!/usr/bin/env python3
"""``undream-healthcheck``: is this container's undream service alive? Exit 0 if so, else 1 and one line why.

    undream-healthcheck worker [--pid PID] [--timeout S]   this host's `undream worker` answers a Celery ping
    undream-healthcheck http URL [--timeout S]             GET URL answers 200 (the dashboard's /api/health)

The images install it as /usr/local/bin/undream-healthcheck; the compose file
and the Kubernetes manifests (deploy/) use it as the services' health check
and liveness probe. A worker is named ``undream-<pid>@<hostname>`` by
:func:`workers.main.worker_argv`, where ``pid`` is the ``undream worker``
process (the prefork parent); without ``--pid`` it is the oldest process of
this host (container) whose command line is ``undream worker``. The ping is
answered by the worker's parent, so a worker busy rendering is healthy; one
that lost its broker is not. Settings come from ``UNDREAM_*`` like the
worker's own (``UNDREAM_BROKER_URL``, ...).
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import urllib.error
import urllib.request
from pathlib import Path


def is_undream_worker(args: list[str]) -> bool:
    """Whether a command line is a Python running ``undream worker`` (the console script or
    ``python -m undream.cli``); an init process that started it (``docker-init -- undream worker``)
    is not."""
    if not args or not Path(args[0]).name.startswith("python"):
        return False
    rest = args[1:]
    if rest[:2] == ["-m", "undream.cli"]:
        rest = rest[2:]
    elif rest and Path(rest[0]).name == "undream":
        rest = rest[1:]
    else:
        return False
    return rest[:1] == ["worker"]


def worker_pid(proc: Path = Path("/proc")) -> int | None:
    """The oldest (lowest) pid on this host whose command line runs ``undream worker``: the prefork
    parent (its children are forked from it later, with the same command line)."""
    pids = []
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:  # gone meanwhile, or not ours to read
            continue
        if is_undream_worker([a.decode(errors="replace") for a in argv if a]):
            pids.append(int(entry.name))
    return min(pids) if pids else None


def check_worker(pid: int | None, timeout: float) -> str | None:
    """None when the worker answers a ping within ``timeout`` s, else why not."""
    from undream.settings import load_settings
    from workers.app import create_celery_app

    pid = pid if pid is not None else worker_pid()
    if pid is None:
        return "no `undream worker` process runs on this host"
    name = f"undream-{pid}@{socket.gethostname()}"
    app = create_celery_app(load_settings())
    try:
        replies = app.control.ping(destination=[name], timeout=timeout)
    except Exception as exc:  # kombu's OperationalError and the transport's own errors
        return f"cannot reach the broker to ping {name}: {' '.join(str(exc).split())}"
    if not any(name in reply for reply in replies):
        return f"worker {name} did not answer a ping within {timeout:g} s"
    return None


def check_http(url: str, timeout: float) -> str | None:
    """None when GET ``url`` answers 200 within ``timeout`` s, else why not."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as resp:
            status = resp.status
    except urllib.error.HTTPError as exc:
        status = exc.code
    except (urllib.error.URLError, OSError) as exc:
        return f"GET {url}: {getattr(exc, 'reason', exc)}"
    return None if status == 200 else f"GET {url}: HTTP {status}"


def build_parser() -> argparse.ArgumentParser:
    """The command line: ``worker [--pid PID] [--timeout S]`` or ``http URL [--timeout S]``."""
    parser = argparse.ArgumentParser(prog="undream-healthcheck", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    worker = sub.add_parser("worker", help="this host's undream worker answers a Celery ping")
    worker.add_argument("--pid", type=int, default=None, help="the `undream worker` process (default: found)")
    worker.add_argument("--timeout", type=float, default=5.0)
    http = sub.add_parser("http", help="GET URL answers 200")
    http.add_argument("url")
    http.add_argument("--timeout", type=float, default=5.0)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the check ``argv`` asks for; print why it failed; the exit status (0 healthy, 1 not)."""
    args = build_parser().parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    why = check_worker(args.pid, args.timeout) if args.what == "worker" else check_http(args.url, args.timeout)
    if why:
        print(f"unhealthy: {why}", file=sys.stderr)
        return 1
    print("healthy")
    return 0


if __name__ == "__main__":
    sys.exit(main())
