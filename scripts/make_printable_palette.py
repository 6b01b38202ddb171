"""Write undream's default printable palette (undream/data/palettes/printable.csv).

The colours are what a CMYK press profile says a print of a grid of ink amounts looks like, in sRGB:
cyan, magenta and yellow each at 0, 25, 50, 75 and 100 % without black (125 patches), black alone at
25, 50, 75 and 100 %, and rich black (every ink at 100 %), converted with littleCMS (Pillow's
ImageCms) from the profile to sRGB, relative colorimetric intent, 8 bits, duplicates dropped. The
profile is Ghostscript's ``default_cmyk.icc`` ("Artifex CMYK SWOP Profile", Debian package
libgs-common, /usr/share/color/icc/ghostscript/); nothing of it is committed, only the colours.

    .venv/bin/python scripts/make_printable_palette.py [--profile PATH] [--out PATH]
"""
from __future__ import annotations

import argparse
import hashlib
import itertools
from pathlib import Path

import numpy as np
from PIL import Image, ImageCms

ROOT = Path(__file__).resolve().parents[1]
PROFILE = Path("/usr/share/color/icc/ghostscript/default_cmyk.icc")
LEVELS = (0, 25, 50, 75, 100)  # % of each ink


def patches() -> list[tuple[int, int, int, int]]:
    """The CMYK ink amounts (0–100 %) of the chart's patches."""
    grid = [(c, m, y, 0) for c, m, y in itertools.product(LEVELS, repeat=3)]
    return grid + [(0, 0, 0, k) for k in LEVELS[1:]] + [(100, 100, 100, 100)]


def to_srgb(profile: Path, cmyk: list[tuple[int, int, int, int]]) -> np.ndarray:
    """N×3 uint8 sRGB of the CMYK patches through ``profile`` (relative colorimetric)."""
    src = ImageCms.getOpenProfile(str(profile))
    transform = ImageCms.buildTransform(src, ImageCms.createProfile("sRGB"), "CMYK", "RGB",
                                        renderingIntent=ImageCms.Intent.RELATIVE_COLORIMETRIC)
    inks = np.round(np.array(cmyk, np.float64) * 255 / 100).astype(np.uint8)[None]
    return np.asarray(ImageCms.applyTransform(Image.fromarray(inks, "CMYK"), transform)).reshape(-1, 3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", type=Path, default=PROFILE)
    ap.add_argument("--out", type=Path, default=ROOT / "undream" / "data" / "palettes" / "printable.csv")
    args = ap.parse_args()
    cmyk = patches()
    rgb = to_srgb(args.profile, cmyk)
    seen, rows = set(), []
    for inks, colour in zip(cmyk, rgb.tolist()):
        if tuple(colour) not in seen:
            seen.add(tuple(colour))
            rows.append((inks, colour))
    digest = hashlib.sha256(args.profile.read_bytes()).hexdigest()
    desc = ImageCms.getProfileDescription(ImageCms.getOpenProfile(str(args.profile))).strip()
    lines = [
        "# undream's default printable palette: sRGB colours (0-255) a CMYK print can reproduce.",
        f"# {len(rows)} patches: C, M, Y each at {', '.join(map(str, LEVELS))} % without black, black alone at",
        "# 25-100 % and rich black, converted from CMYK to sRGB (relative colorimetric, littleCMS via",
        f"# Pillow's ImageCms) with the profile {desc!r} (Ghostscript's default_cmyk.icc,",
        f"# Debian package libgs-common; SHA-256 {digest}).",
        "# Written by scripts/make_printable_palette.py; the comment after each line is the patch's C,M,Y,K %.",
        "r,g,b",
    ] + [f"{r},{g},{b}  # {c},{m},{y},{k}" for (c, m, y, k), (r, g, b) in rows]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"{args.out}: {len(rows)} colours")


if __name__ == "__main__":
    main()
