#!/usr/bin/env python
"""Screenshots of an `undream report` folder as a reader's browser shows it (headless Chromium, 1400 × 900).

    .venv/bin/undream report /tmp/mj/b --out /tmp/rep_main
    .venv/bin/python scripts/report_screenshots.py /tmp/rep_main --out docs/report_main.png \\
        [--full docs/report_main_full.png --full-width 700]

``--out``: the top of the page, what the window shows on opening it (1400 × 900 px PNG, one CSS px a
pixel). ``--full``: the whole page, scaled down to ``--full-width`` px wide (images below the fold
loaded first). Both with a palette of ``--colors`` (256: a docs picture a quarter the bytes). Needs
Debian's chromium and chromium-driver and selenium (undream.report.browser); prints what it wrote and
each picture's size.
"""
from __future__ import annotations

import argparse
import io
import sys
import tempfile
from pathlib import Path

from PIL import Image

from undream.errors import UndreamError
from undream.report import browser


def _save(png: bytes, out: Path, colors: int, width: int | None = None) -> tuple[int, int]:
    """Write ``png`` to ``out`` (scaled to ``width`` px wide, keeping its aspect, when given; with a
    palette of ``colors``, 0: true colour); returns its size in px."""
    with Image.open(io.BytesIO(png)) as img:
        pic = img.convert("RGB")
    if width is not None and pic.width > width:
        pic = pic.resize((width, max(1, round(pic.height * width / pic.width))), Image.LANCZOS)
    out.parent.mkdir(parents=True, exist_ok=True)
    if colors:
        pic.quantize(colors=colors, method=Image.Quantize.FASTOCTREE).save(out, format="PNG", optimize=True)
    else:
        pic.save(out, format="PNG", optimize=True)
    return pic.size


def screenshots(report: Path, out: Path, full: Path | None = None, full_width: int = 700,
                colors: int = 256) -> dict[Path, tuple[int, int]]:
    """Open ``report``'s index.html and write the screenshots (see the module docstring); returns
    each file written with its size in px. UndreamError when the folder holds no page or no browser runs."""
    page = Path(report) / "index.html"
    if not page.is_file():
        raise UndreamError(f"{report}: no index.html (give the --out folder of `undream report`)")
    url = page.resolve().as_uri()
    written = {}
    with tempfile.TemporaryDirectory(prefix="undream-chromium-") as profile, browser.chromium(Path(profile)) as driver:
        written[out] = _save(browser.top_png(driver, url), out, colors)
        if full is not None:
            written[full] = _save(browser.full_png(driver, url), full, colors, full_width)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="a folder written by `undream report --out`")
    parser.add_argument("--out", type=Path, required=True, help="the top of the page (.png, 1400 × 900)")
    parser.add_argument("--full", type=Path, help="the whole page, scaled down (.png)")
    parser.add_argument("--full-width", type=int, default=700, help="the whole page's width in px (default 700)")
    parser.add_argument("--colors", type=int, default=256,
                        help="a palette of this many colours, a quarter of the bytes (default 256; 0: true colour)")
    args = parser.parse_args(argv)
    try:
        written = screenshots(args.report, args.out, args.full, args.full_width, args.colors)
    except UndreamError as err:
        print(f"report_screenshots: {err}", file=sys.stderr)
        return 2
    for path, (w, h) in written.items():
        print(f"wrote {path} ({w} × {h} px)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
