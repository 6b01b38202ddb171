#!/usr/bin/env python3
"""Fetch the CMYK print profile of ``gamut: default`` into undream's cache, checked.

Reads ``deploy/profiles.lock.json`` (a pinned Debian package, the SHA-256 of
every file taken) and fetches with :mod:`fetch_models`'s rules (``apt-get
download``, ``dpkg-deb -x``; a file already there with the right checksum is
not fetched again) into ``CACHE/profiles`` (``CACHE``: ``$XDG_CACHE_HOME/undream``,
default ``~/.cache/undream``, or ``--cache``), where
:func:`undream.printing.profiles.default_profile` finds it. Errors are one line.
Run by ``deploy/setup.sh``; by hand: ``.venv/bin/python deploy/fetch_profiles.py [--cache DIR] [--check]``.
Standard library only.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from fetch_models import FetchError, default_cache, fetch, missing  # noqa: E402

LOCK = HERE / "profiles.lock.json"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=None, help="cache folder (default $XDG_CACHE_HOME/undream)")
    ap.add_argument("--check", action="store_true", help="only say what is missing; exit 1 if anything is")
    args = ap.parse_args(argv)
    cache = args.cache or default_cache()
    packages = json.loads(LOCK.read_text(encoding="utf-8"))["packages"]
    if args.check:
        gaps = [f"{p['package']}: {src}" for p in packages for src in missing(p, cache)]
        print("\n".join(gaps) or f"fetch_profiles: everything is in {cache / 'profiles'}")
        return 1 if gaps else 0
    try:
        for pkg in packages:
            n = fetch(pkg, cache)
            print(f"fetch_profiles: {pkg['package']} {pkg['version']}: "
                  f"{f'{n} file(s) fetched' if n else 'already in the cache'}")
    except (FetchError, OSError, StopIteration) as err:
        print(f"fetch_profiles: error: {err or 'the download left no archive'}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
