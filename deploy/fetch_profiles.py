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

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from fetch_models import fetch_locked  # noqa: E402

LOCK = HERE / "profiles.lock.json"


def main(argv: list[str] | None = None) -> int:
    return fetch_locked(argv, LOCK, "fetch_profiles", "profiles")


if __name__ == "__main__":
    sys.exit(main())
