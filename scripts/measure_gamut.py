"""Measure how far a CMYK profile's gamut projection moves colours (the numbers in docs/printing.md).

Over all 2²⁴ 8-bit sRGB colours: the share the profile prints (round trip within the tolerance),
how far the single ICC round trip R moves colours, how far a colour that came back from one trip
moves on a second (why R alone is no projection), how far the projection P moves the colours it
changes, how far P lies from R, where pure red, green, blue, black and white go, and whether P is
idempotent. Default: the profile setup fetched (``gamut: default``).

    .venv/bin/python scripts/measure_gamut.py [--profile PATH]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from undream.printing.gamut import _cube, _indices, build_gamut, round_trip
from undream.printing.profiles import default_profile
from undream.settings import load_local


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", type=Path, default=None, help="a CMYK profile (default: gamut: default's)")
    args = ap.parse_args()
    profile = args.profile or default_profile(load_local().undream_cache)
    t = time.perf_counter()
    gamut = build_gamut(profile)
    built = time.perf_counter() - t
    cube = _cube().reshape(-1, 3).astype(np.int16)
    back = round_trip(_cube(), profile).reshape(-1, 3).astype(np.int16)
    again = back[_indices(back.astype(np.uint8))]
    table = gamut.table.astype(np.int16)
    out = ~gamut.inside

    def stats(name: str, d: np.ndarray) -> None:
        print(f"{name}: median {np.median(d):.0f}, 99th percentile {np.percentile(d, 99):.0f}, most {d.max()} levels")

    print(f"{gamut.name} ({profile}); built in {built:.1f} s; tolerance {gamut.tolerance} levels (L-infinity)")
    print(f"printable: {gamut.inside.mean():.1%} of the 8-bit sRGB cube")
    stats("round trip R moves a colour", np.abs(back - cube).max(axis=1))
    stats("a second trip moves a round-tripped colour", np.abs(again - back).max(axis=1))
    stats("P moves a colour it changes", np.abs(table - cube).max(axis=1)[out])
    stats("P lies from R (colours it changes)", np.abs(table - back).max(axis=1)[out])
    for name, rgb in (("red", (255, 0, 0)), ("green", (0, 255, 0)), ("blue", (0, 0, 255)),
                      ("black", (0, 0, 0)), ("white", (255, 255, 255))):
        i = (rgb[0] << 16) | (rgb[1] << 8) | rgb[2]
        print(f"{name} {rgb} -> {tuple(int(v) for v in gamut.table[i])}")
    print(f"idempotent on the grid: {bool(np.array_equal(gamut.table[_indices(gamut.table)], gamut.table))}")


if __name__ == "__main__":
    main()
