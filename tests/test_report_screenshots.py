"""scripts/report_screenshots.py: a synthetic multi-condition run's report (tests/conditions_data.py, 4
conditions × 8 views of 32 px, no rendering) shot in headless Chromium: the top of the page has the
window's size and is not blank, the whole page is scaled to the width asked.

Without Chromium the test skips saying why, and fails under ``UNDREAM_REQUIRE_SERVICES``.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from browser_support import WINDOW  # noqa: E402
from conditions_data import conditions_output  # noqa: E402
from conftest import service_missing  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_the_script_shoots_the_top_of_a_report_and_the_whole_page(tmp_path):
    from undream.cli import main
    from undream.report import browser

    why = browser.missing()
    if why:
        service_missing(why)
    conditions_output(tmp_path / "run", 4, 8, 32, 1)
    res = CliRunner().invoke(main, ["report", str(tmp_path / "run"), "--out", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    top, full = tmp_path / "shots" / "top.png", tmp_path / "shots" / "full.png"
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_screenshots.py"), str(tmp_path / "rep"),
                           "--out", str(top), "--full", str(full), "--full-width", "500"],
                          capture_output=True, text=True, cwd=ROOT, timeout=180)
    assert done.returncode == 0, done.stderr
    assert f"wrote {top} (1400 × 900 px)" in done.stdout
    with Image.open(top) as img:
        assert img.size == WINDOW
        pixels = np.asarray(img.convert("RGB"))
    assert pixels.std() > 20 and len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50  # text, tables, frames
    assert (pixels[:60] < 128).any()  # the title's dark text at the top, not an empty page
    with Image.open(full) as img:
        assert img.width == 500 and img.height > 900 * 500 / 1400  # the page is longer than one screen


def test_a_folder_without_a_page_is_one_line(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_screenshots.py"), str(tmp_path),
                           "--out", str(tmp_path / "x.png")], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "no index.html" in done.stderr, done.stderr
    assert not (tmp_path / "x.png").exists()
