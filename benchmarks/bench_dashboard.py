"""Benchmark the dashboard on a big farm database, measured in one run:

    python benchmarks/bench_dashboard.py [--runs 200] [--frames 64] [--iterations 100] [--repeat 5] [--cold 3]

Builds (through the Store API, in a temporary folder, SQLite) ``--runs`` runs:
one with ``--frames`` frames × ``--iterations`` iterations (done, with its
evaluation) and the others small (4 frames, 5 iterations, every state), then
starts ``undream dashboard`` on it and prints, for the runs list (all runs)
and the big run's page: the HTML's size and the time to serve it (first and
median of ``--repeat`` over HTTP), the time for the page with every picture
it shows (first load, pictures uncached, then again), and where Chromium is
installed, the browser's own load time (navigation start → load event, the
page rendered with the pictures in view; frames further down load lazily),
on ``--cold`` fresh servers (each a first visit, with a fresh browser; and their median) and
again once a server's caches are warm. Prints the machine's load before and after (and after each
first visit). Not a test: it prints numbers and asserts nothing.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Iterator

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200, help="runs in the database (one of them big)")
    p.add_argument("--frames", type=int, default=64, help="frames of the big run")
    p.add_argument("--iterations", type=int, default=100, help="iterations of the big run")
    p.add_argument("--repeat", type=int, default=5, help="requests per page for the median")
    p.add_argument("--cold", type=int, default=3,
                   help="first visits in Chromium, each on a fresh server (the median is printed too)")
    return p.parse_args(argv)


def build(blobs: Path, args: argparse.Namespace) -> str:
    """The database; returns the big run's id."""
    from dashboard_data import RunShape, add_run

    from undream.store import RUN_STATUSES, open_store

    rng = np.random.default_rng(0)
    with open_store(None, blobs) as store:
        big = add_run(store, RunShape("big", "done", args.frames, args.iterations, args.iterations,
                                      texture=(64, 128)), rng)
        for i in range(args.runs - 1):
            status = RUN_STATUSES[i % len(RUN_STATUSES)]
            done = {"queued": 0, "evaluating": 5, "done": 5}.get(status, 2)
            add_run(store, RunShape(f"small-{i:03d}", status, 4, 5, done), rng)
    return big


def _get(url: str) -> tuple[float, bytes]:
    t0 = time.perf_counter()
    with urllib.request.urlopen(url, timeout=60) as res:
        body = res.read()
    return time.perf_counter() - t0, body


def _pictures(base: str, html: bytes) -> list[str]:
    return [base + src.replace("&amp;", "&") for src in re.findall(r'<img[^>]* src="([^"]+)"', html.decode())]


def measure(base: str, path: str, repeat: int) -> dict[str, float]:
    first, html = _get(base + path)
    times = [_get(base + path)[0] for _ in range(repeat)]
    pictures = _pictures(base, html)
    t0 = time.perf_counter()
    for url in pictures:
        _get(url)
    cold = first + time.perf_counter() - t0
    t0 = time.perf_counter()
    _get(base + path)
    for url in pictures:
        _get(url)
    return {"kb": len(html) / 1024, "first": first, "median": statistics.median(times),
            "pictures": len(pictures), "with_pictures_cold": cold, "with_pictures_warm": time.perf_counter() - t0}


def browser_load(base: str, paths: list[str], profile: Path) -> dict[str, float] | None:
    """Chromium's navigation start → load event for each path (None without Chromium or selenium)."""
    if not (os.access("/usr/bin/chromium", os.X_OK) and os.access("/usr/bin/chromedriver", os.X_OK)):
        return None
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        return None
    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", f"--user-data-dir={profile}", "--window-size=1400,1000"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    try:
        out = {}
        for path in paths:
            driver.get(base + path)
            out[path] = driver.execute_script(
                "const t = performance.getEntriesByType('navigation')[0]; return t.loadEventEnd - t.startTime;") / 1000
        return out
    finally:
        driver.quit()


def _load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


@contextlib.contextmanager
def serve(blobs: Path) -> Iterator[str]:
    """``undream dashboard`` on the database in ``blobs``, a fresh process; yields its base URL once
    ``/api/health`` answers (what the server does as it starts is not measured)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "dashboard", "--port", str(port),
                             "--blobs", str(blobs)], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        while True:
            try:
                _get(base + "/api/health")
                break
            except OSError:
                time.sleep(0.2)
        yield base
    finally:
        proc.terminate()
        proc.wait(20)


def _loads_line(label: str, loads: dict[str, float]) -> str:
    return f"Chromium, navigation start → load event ({label}): " + ", ".join(
        f"{'runs list' if p == '/' else 'big run page'} {s:.3f} s" for p, s in loads.items())


def cold_visits(blobs: Path, paths: list[str], times: int, tmp: Path) -> list[dict[str, float]]:
    """Chromium's load of ``paths`` on ``times`` fresh servers (a fresh browser each); printed as it goes."""
    out = []
    for i in range(times):
        with serve(blobs) as base:
            loads = browser_load(base, paths, tmp / f"chromium-cold-{i}")
        if loads is None:
            return []
        print(_loads_line(f"first visit {i + 1} of {times}, fresh server", loads) + f"; {_load()}")
        out.append(loads)
    return out


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    print(f"load before: {_load()}")
    with tempfile.TemporaryDirectory(prefix="undream-bench-dash-") as tmp:
        blobs = Path(tmp) / "blobs"
        t0 = time.perf_counter()
        big = build(blobs, args)
        print(f"database: {args.runs} runs, the big one {args.frames} frames × {args.iterations} iterations "
              f"({args.frames * args.iterations} frame jobs); built in {time.perf_counter() - t0:.1f} s")
        paths = ["/", f"/runs/{big}"]
        cold = cold_visits(blobs, paths, args.cold, Path(tmp))
        if cold:
            print(_loads_line(f"first visit, median of {len(cold)} fresh servers",
                              {p: statistics.median(c[p] for c in cold) for p in paths}))
        with serve(blobs) as base:
            pages = {"runs list (/)": "/", "big run page": f"/runs/{big}", "GET /api/runs": "/api/runs",
                     "GET /api/runs/<big>/jobs": f"/api/runs/{big}/jobs"}
            print(f"{'page':<26} {'KiB':>7} {'first s':>8} {'median s':>9} {'pictures':>9} "
                  f"{'+pictures cold s':>17} {'+pictures warm s':>17}")
            for name, path in pages.items():
                m = measure(base, path, args.repeat)
                print(f"{name:<26} {m['kb']:>7.0f} {m['first']:>8.3f} {m['median']:>9.3f} {m['pictures']:>9d} "
                      f"{m['with_pictures_cold']:>17.3f} {m['with_pictures_warm']:>17.3f}")
            warm = browser_load(base, paths, Path(tmp) / "chromium-warm")
        if warm is None:
            print("browser load: Chromium or selenium missing, not measured")
        else:
            print(_loads_line("server caches warm", warm))
    print(f"load after: {_load()}")


if __name__ == "__main__":
    main()
