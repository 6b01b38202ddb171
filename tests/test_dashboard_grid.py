"""The dashboard's run page of a 16-condition run (384 frames of 64 px; tests/conditions_data.py, no
rendering): the conditions table most fooled first, the frames a page of whole conditions at a time
(``?page=N``), a frame shown full size (``?frame=F``), and the page's size in a real headless Chromium
(1400 × 900: no horizontal scrolling, at most 5,400 px tall), served by ``undream dashboard``.
"""
from __future__ import annotations

import html
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from browser_support import assert_fits, chromium, page_size  # noqa: E402
from conditions_data import conditions_output  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONDITIONS, VIEWS, HELD = 16, 24, 4
PER_PAGE = 96 // VIEWS  # conditions on a page (undream.dashboard.framegrid.FRAMES_PER_PAGE frames)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("dash-grid")
    made = conditions_output(root / "run", CONDITIONS, VIEWS, 64, HELD)
    return {**made, "store": root / "run" / "store", "root": root}


@pytest.fixture(scope="module")
def client(run):
    from undream.dashboard import create_app
    from undream.settings import load_settings

    return create_app(load_settings(env={"UNDREAM_BLOB_URL": str(run["store"])})).test_client()


def _rows(page: str) -> list[tuple[str, list[int]]]:
    """The grid's rows: (condition, frame positions of its thumbnails)."""
    grid = page[page.index('id="frame-grid"'):]
    parts = re.split(r'<div class="cond" id="row-\d+">', grid[:grid.index("</div>\n</div>") + 20])[1:]
    return [(re.search(r"<b>([^<]+)</b>", p).group(1), [int(f) for f in re.findall(r'data-frame="(\d+)"', p)])
            for p in parts]


def test_the_run_page_shows_a_page_of_whole_conditions(run, client):
    conditions = run["results"]["conditions"]
    pages = []
    for page in range(1, CONDITIONS // PER_PAGE + 1):
        res = client.get(f"/runs/{run['run_id']}?page={page}")
        assert res.status_code == 200
        text = res.get_data(as_text=True)
        rows = _rows(text)
        assert [name for name, _ in rows] == [c["name"] for c in conditions[(page - 1) * PER_PAGE:page * PER_PAGE]]
        assert all(frames == c["frames"] for (_, frames), c in zip(rows, conditions[(page - 1) * PER_PAGE:]))
        assert f"frames, page {page} of {CONDITIONS // PER_PAGE}" in text
        job_rows = re.findall(r"<tr><th>(\d+)</th>", text[text.index('id="job-grid"'):])
        assert [int(f) for f in job_rows] == [f for _, frames in rows for f in frames]  # the page's frames only
        pages.append(text)
    table = pages[0][pages[0].index('id="conditions"'):]
    shown = re.findall(r'<tr data-condition="([^"]+)"><td><a href="\?page=(\d)#row-(\d+)">', table)
    rates = {c["name"]: c["attack_success"]["success_rate"] for c in conditions}
    assert [rates[name] for name, _, _ in shown] == sorted(rates.values(), reverse=True)  # most fooled first
    for name, page, row in shown:  # each links to the page and row that show it
        index = [c["name"] for c in conditions].index(name)
        assert (int(page), int(row)) == (index // PER_PAGE + 1, index)
    assert "held-out conditions (96)" in pages[0]


def test_a_chosen_frame_is_shown_full_size_on_its_page(run, client):
    text = client.get(f"/runs/{run['run_id']}?frame=100").get_data(as_text=True)
    assert "frames, page 2 of 4" in text and 'class="pair" data-frame="100"' in text
    assert len(re.findall(r'class="pair"', text)) == 1
    assert "Pick a frame in the grid" in client.get(f"/runs/{run['run_id']}").get_data(as_text=True)


def test_a_detector_runs_grid_names_what_it_saw_instead(run, client):
    from dashboard_data import add_detector_run
    from undream.store import open_store

    with open_store(None, run["store"]) as store:
        run_id = add_detector_run(store)  # every adversarial frame missed, an umbrella its best box
    text = client.get(f"/runs/{run_id}").get_data(as_text=True)
    cells = re.findall(r'<a class="cell (a|h) (ok|no)[^>]*title="([^"]*)".*?<span>([^<]*)</span>', text)
    assert [c[1:] for c in cells] == [("no", f"frame {f} · attacked · adversarial: missed, best box umbrella 0.42",
                                       "✗ umbrella") for f in range(2)]
    assert len(re.findall(r'class="pair"', text)) == 2  # two frames: both pairs full size, boxes over them


@pytest.mark.parametrize("query, words", [("page=0", "page '0': must be a whole number from 1"),
                                          ("page=x", "page 'x': must be a whole number from 1"),
                                          ("page=5", "page 5: the run's frames fill 4 pages"),
                                          ("frame=384", "frame 384: the run has frames 0 to 383")])
def test_a_bad_page_or_frame_is_a_400_naming_it(run, client, query, words):
    res = client.get(f"/runs/{run['run_id']}?{query}")
    assert res.status_code == 400 and words in html.unescape(res.get_data(as_text=True))


@pytest.fixture(scope="module")
def site(run):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "UNDREAM_BLOB_URL": str(run["store"])}
    env.pop("UNDREAM_DATABASE_URL", None)
    log = open(run["root"] / "dashboard.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "dashboard", "--port", str(port)],
                            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    end = time.monotonic() + 60
    while True:
        try:
            urllib.request.urlopen(base + "/api/health", timeout=5).read()
            break
        except OSError:
            assert proc.poll() is None and time.monotonic() < end, (run["root"] / "dashboard.log").read_text()
            time.sleep(0.2)
    yield base
    proc.terminate()
    proc.wait(20)
    log.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    yield from chromium(tmp_path_factory.mktemp("chromium-profile"))


def test_the_run_page_fits_the_window_and_six_screens(run, site, browser, tmp_path):
    from selenium.webdriver.common.by import By

    url = f"{site}/runs/{run['run_id']}"
    for query in ("", "?page=4", "?frame=100"):
        size = page_size(browser, url + query)
        print(f"dashboard run page{query or ' (page 1)'}: {size}")
        assert_fits(size)
    cells = browser.find_elements(By.CSS_SELECTOR, "#frame-grid a.cell")
    assert len(cells) == PER_PAGE * VIEWS
    lines = {round(c.rect["y"]) for c in cells[:VIEWS]}
    assert len(lines) == 2  # 24 views in two lines of 12
    browser.find_element(By.ID, "next-frames-top").click()  # to page 3
    end = time.monotonic() + 20
    while "frames, page 3 of 4" not in browser.find_element(By.ID, "pager-top").text:
        assert time.monotonic() < end, "the next page of frames"
        time.sleep(0.1)
    browser.find_elements(By.CSS_SELECTOR, "#frame-grid a.cell")[5].click()  # a frame, full size
    end = time.monotonic() + 20
    while not browser.find_elements(By.CSS_SELECTOR, "#frames .pair img"):
        assert time.monotonic() < end, "the chosen frame's pair"
        time.sleep(0.1)
    assert browser.find_element(By.CSS_SELECTOR, "#frames .pair").get_attribute("data-frame") == str(2 * 96 + 5)
    browser.save_screenshot(str(tmp_path / "run_page.png"))
