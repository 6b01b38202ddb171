"""``undream report`` of a 16-condition run (384 frames of 64 px; tests/conditions_data.py, no rendering)
with an `undream evaluate --json` file of 8 other scenes: the headline in counts, the conditions most
fooled first, the grid of conditions × views, the transfer table, and the page's size in a real headless Chromium (1400 × 900 window: no horizontal scrolling, ≤ 5,400 px tall).

Without Chromium the browser test skips saying why, and fails under ``UNDREAM_REQUIRE_SERVICES``.
"""
from __future__ import annotations

import csv
import io
import json
import re
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from browser_support import assert_fits, chromium, page_size  # noqa: E402
from conditions_data import conditions_output  # noqa: E402

CONDITIONS, VIEWS, HELD = 16, 24, 4


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> dict:
    from undream.cli import main

    root = tmp_path_factory.mktemp("grid")
    made = conditions_output(root / "run", CONDITIONS, VIEWS, 64, HELD)
    evaluation = root / "evaluate.json"  # as `undream evaluate --json` writes it: 8 held-out condition specs
    evaluation.write_text(json.dumps({"texture": str(root / "run"), "frames": None, "rows": [
        {"scene": f"examples/conditions/held_out_{i}.yaml", "victim": "bundled:classifier", "sim": "mitsuba",
         "texture": str(root / "run"), "split": split, "frames": n, "metric": "accuracy", "benign": 0.9,
         "adversarial": 0.1 * i} for i in range(8) for split, n in (("all", 24), ("attacked", 18), ("held_out", 6))]}))
    res = CliRunner().invoke(main, ["report", str(root / "run"), "--out", str(root / "rep"),
                                    "--evaluation", str(evaluation)])
    assert res.exit_code == 0, res.output
    return {**made, "out": root / "rep", "html": (root / "rep" / "index.html").read_text()}


def _section(html: str, start: str, end: str) -> str:
    part = html[html.index(start):]
    return part[:part.index(end)]


def test_the_headline_counts_frames_and_lists_none(report):
    table = _section(report["html"], "<table id=headline>", "</table>")
    cells = re.findall(r"<tr><td>([^<]+)</td><td class=n>(\d+)</td>", table)
    assert cells == [("attacked frames", "216"), ("held-out frames", "72"), ("held-out conditions", "96"),
                     ("all frames", "384")]
    assert len(table) < 1500 and "accuracy: benign → adversarial" in table  # no frame numbers in it
    rows = {r["split"]: r for r in csv.DictReader(io.StringIO((report["out"] / "headline.csv").read_text()))}
    assert rows["held-out conditions"]["frames"].split() == [str(f) for f in range(288, 384)]


def test_the_conditions_table_puts_the_most_fooled_first(report):
    table = _section(report["html"], "<table id=conditions", "</table>")
    shown = re.findall(r"<tr><td>([^<]+)</td><td>(attacked|held out)</td>", table)
    success = {c["name"]: c["attack_success"]["success_rate"] for c in report["results"]["conditions"]}
    assert sorted(name for name, _ in shown) == sorted(success)
    rates = [success[name] for name, _ in shown]
    assert rates == sorted(rates, reverse=True) and rates[0] > rates[-1]
    held = {c["name"] for c in report["results"]["conditions"] if c["held_out"]}
    assert {name for name, tag in shown if tag == "held out"} == held and len(held) == HELD
    listed = list(csv.DictReader(io.StringIO((report["out"] / "conditions.csv").read_text())))
    assert [r["condition"] for r in listed] == [c["name"] for c in report["results"]["conditions"]]  # run order


def test_the_grid_has_a_row_per_condition_and_a_linked_thumbnail_per_view(report):
    html, out = report["html"], report["out"]
    rows = re.split(r'<div class=cond id="row-\d+">', _section(html, "<div class=grid>", "<h2>"))[1:]
    conditions = report["results"]["conditions"]
    assert len(rows) == CONDITIONS
    held_views = set(report["results"]["held_out"]["frames"])
    per_frame = report["results"]["adversarial"]["per_frame"]
    for row, cond in zip(rows, conditions):
        assert f"<b>{cond['name']}</b>" in row and ("held out</span>" in row) == cond["held_out"]
        adversarial = row[:row.index('class="cells benign"')]
        cells = re.findall(r'<a class="cell (a|h) (ok|no)" href="(frames/frame_(\d{4})\.png)"[^>]*>'
                           r'<img src="(thumbs/adversarial/frame_\d{4}\.png)"', adversarial)
        assert [int(c[3]) for c in cells] == cond["frames"]  # views across, in order
        for split, state, link, index, thumb in cells:
            f = int(index)
            assert split == ("h" if cond["held_out"] or f in held_views else "a")
            assert state == ("ok" if per_frame[f]["correct"] else "no")
            assert (out / link).is_file() and (out / thumb).is_file()
        benign = row[row.index('class="cells benign"'):]
        assert len(re.findall(r'src="thumbs/benign/frame_\d{4}\.png"', benign)) == VIEWS
    frames = list(csv.DictReader(io.StringIO((out / "frames.csv").read_text())))
    assert (frames[30]["condition"], frames[30]["view"]) == (conditions[1]["name"], "6")


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    yield from chromium(tmp_path_factory.mktemp("chromium-profile"))


def test_the_transfer_table_has_a_row_per_evaluated_scene(report):
    table = _section(report["html"], "<table id=transfer", "</table>")
    assert table.count("<tr>") == 1 + 1 + 8 and "held_out_7.yaml" in table and table.count("<td>[1]</td>") == 8
    from PIL import Image

    assert 'src="transfer.png"' in report["html"]
    with Image.open(report["out"] / "transfer.png") as chart:  # a pair of bars per row: taller with more rows
        assert chart.width == 700 and chart.height > 100 * (0.9 + 0.24 * 9)


def test_the_report_fits_the_window_and_six_screens(report, browser, tmp_path):
    url = (report["out"] / "index.html").as_uri()
    size = page_size(browser, url)
    assert_fits(size)
    print(f"report of {CONDITIONS} conditions × {VIEWS} views: {size}")
    images = browser.execute_script("return document.images.length;")
    assert images >= CONDITIONS * VIEWS  # every adversarial thumbnail is on the page
    browser.get(url + "#benign-3")  # a row's benign frames, shown without a script
    shown = browser.execute_script("return getComputedStyle(document.getElementById('benign-3')).display;")
    hidden = browser.execute_script("return getComputedStyle(document.getElementById('benign-4')).display;")
    assert (shown, hidden) == ("grid", "none")
    browser.save_screenshot(str(tmp_path / "report.png"))


SPEC = {  # a tiny ball in a park, orbited: 4 frames of 16 px per condition
    "name": "ball", "seed": 3, "frames": 4, "fps": 4,
    "camera": {"fov": 40, "resolution": [16, 16],
               "path": {"type": "orbit", "center": [0, 0, 0], "radius": 2.6, "height": 1.0,
                        "start_deg": 0, "end_deg": 90},
               "look_at": "object", "look_at_offset": [0, 0.4, 0]},
    "object": {"asset": {"name": "ball", "mesh": "builtin:sphere",
                         "texture": {"resolution": [16, 8], "init": [0.5, 0.5, 0.5]}},
               "path": {"type": "static", "position": [0, 0, 0]}},
    "environment": {"weather": "clear", "time_of_day": 14.0, "background": "park"},
}


def test_a_real_multi_condition_run_reports_its_conditions_as_grid_rows(tmp_path, mi):
    """`undream run` over 3 conditions (one held out whole, every 4th view of the others held out),
    then `undream report`: the grid's rows are results.json's conditions, cells its frames in order."""
    import subprocess

    from farm_support import make_victim, run_config, write_yaml
    from undream.cli import main

    cfg = run_config(write_yaml(tmp_path / "ball.yaml", SPEC), make_victim(tmp_path / "victim"), name="grid",
                     steps=1, holdout="auto",
                     conditions={"grid": {"environment.weather": ["clear", "fog", "rain"]}, "holdout": ["weather_rain"]})
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(tmp_path / "run.yaml", cfg)),
                          "--out", str(out), "--no-progress"], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    res = CliRunner().invoke(main, ["report", str(out), "--out", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    html = (tmp_path / "rep" / "index.html").read_text()
    rows = re.split(r'<div class=cond id="row-\d+">', _section(html, "<div class=grid>", "<h2>"))[1:]
    assert len(rows) == len(results["conditions"]) == 3
    held = set(results["held_out"]["frames"]) | set(results["held_out_conditions"]["frames"])
    for row, cond in zip(rows, results["conditions"]):
        adversarial = row[:row.index('class="cells benign"')]
        cells = [(split, int(f)) for split, f in re.findall(r'<a class="cell (a|h) \w+" href="frames/frame_(\d{4})\.png"',
                                                               adversarial)]
        assert [f for _, f in cells] == cond["frames"] and len(cells) == 4
        assert [split for split, _ in cells] == ["h" if f in held else "a" for f in cond["frames"]]
        assert ("held out</span>" in row) == cond["held_out"] == (cond["name"] == "weather_rain")
    assert (tmp_path / "rep" / "conditions.csv").is_file()
