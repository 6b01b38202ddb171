"""The dashboard in a real headless Chromium: runs list → run page → sweep page, clicking through.

``undream dashboard`` runs as a subprocess on a database holding a run in
every state and a sweep (tests/dashboard_data.py); Debian's ``chromium`` and
``chromium-driver`` drive it through selenium (no Selenium Manager, no
network). Screenshots go to the test's tmp dir (``<tmp>/screens/*.png``).
Without Chromium the tests skip saying why, and fail under
``UNDREAM_REQUIRE_SERVICES`` (CI).
"""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import service_missing  # noqa: E402
from dashboard_data import build_farm  # noqa: E402

from undream.store import open_store  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
TOKEN = "browser-secret-0123"
WAIT_S = 20.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The dashboard of a fresh farm database, served by ``undream dashboard``: (base URL, ids, blobs)."""
    root = tmp_path_factory.mktemp("dash-browser")
    blobs = root / "blobs"
    with open_store(None, blobs) as store:
        ids = build_farm(store, frames=6, steps=8)
    port = _free_port()
    env = {**os.environ, "UNDREAM_DASHBOARD_TOKEN": TOKEN, "UNDREAM_BLOB_URL": str(blobs)}
    log = open(root / "dashboard.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "undream.cli", "dashboard", "--port", str(port)],
                            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    end = time.monotonic() + 60
    while True:
        try:
            urllib.request.urlopen(base + "/api/health", timeout=5).read()
            break
        except OSError:
            assert proc.poll() is None and time.monotonic() < end, (root / "dashboard.log").read_text()
            time.sleep(0.2)
    yield base, ids, blobs
    proc.terminate()
    proc.wait(20)
    log.close()


@pytest.fixture(scope="module")
def browser(site, tmp_path_factory):
    missing = [p for p in (CHROMIUM, CHROMEDRIVER) if not os.access(p, os.X_OK)]
    if missing:
        service_missing(f"{' and '.join(missing)} missing (apt-get install chromium chromium-driver; "
                        "deploy/setup.sh does)")
    pytest.importorskip("selenium", reason="selenium not installed (pip install 'undream[test]')")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tmp_path_factory.mktemp("chromium-profile")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", f"--user-data-dir={profile}", "--window-size=1400,1000"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


@pytest.fixture
def shots(tmp_path):
    folder = tmp_path / "screens"
    folder.mkdir()
    return folder


def _wait(cond, what: str, timeout: float = WAIT_S):
    """Poll ``cond`` until it is truthy; an element replaced by the page's refresh meanwhile is a retry."""
    from selenium.common.exceptions import StaleElementReferenceException

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            value = cond()
        except StaleElementReferenceException:
            value = None
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _images_loaded(driver) -> bool:
    return driver.execute_script(
        "return Array.from(document.images).every(i => i.complete && i.naturalWidth > 0);")


def _screenshot(driver, folder: Path, name: str) -> Path:
    """A screenshot of the whole page, 1400 CSS px wide (Chromium's DevTools protocol sizes the view)."""
    driver.execute_script("window.scrollTo(0, 0)")
    size = driver.execute_cdp_cmd("Page.getLayoutMetrics", {})["cssContentSize"]
    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
        "width": 1400, "height": min(int(size["height"]) + 1, 8000), "deviceScaleFactor": 1, "mobile": False})
    path = folder / f"{name}.png"
    try:
        _wait(lambda: _images_loaded(driver), f"every picture of {name} (lazy ones too, the view is the page)")
        assert driver.save_screenshot(str(path))
    finally:
        driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})
    return path


def _no_console_errors(driver) -> None:
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert errors == [], errors


def _by(driver, css: str):
    from selenium.webdriver.common.by import By

    return driver.find_elements(By.CSS_SELECTOR, css)


def test_runs_list_to_run_page_to_sweep_page(site, browser, shots):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.support.ui import Select

    base, ids, _ = site
    browser.get(base + "/")
    rows = _by(browser, "#runs-table tbody tr")
    assert len(rows) == 12
    assert {r.get_attribute("data-status") for r in rows} == \
        {"queued", "running", "evaluating", "done", "failed", "cancelled"}
    assert len(_by(browser, "#runs-table svg.spark polyline")) == 10  # not queued (no loss) nor cancelled (one)
    done = _by(browser, f'tr[data-run="{ids.runs["done"]}"] td.result')[0].text
    assert done == "100.0 % → 0.0 % held-out", done  # frame 3 held out; frames 0 to 3 fooled
    _screenshot(browser, shots, "01_runs")

    Select(_by(browser, "#filter-status")[0]).select_by_value("failed")
    _by(browser, "#filters button")[0].click()
    _wait(lambda: len(_by(browser, "#runs-table tbody tr")) == 1, "the failed runs only")
    assert _by(browser, "#runs-table tbody tr")[0].get_attribute("data-run") == ids.runs["failed"]
    _screenshot(browser, shots, "02_runs_failed")

    browser.get(base + "/")
    _by(browser, f'tr[data-run="{ids.runs["running"]}"] a.run-link')[0].click()
    _wait(lambda: _by(browser, "#job-grid"), "the run page")
    _wait(lambda: _images_loaded(browser), "the run page's charts and textures")
    assert "iteration 4 of 8" in _by(browser, "#run-progress")[0].text
    assert len(_by(browser, "#texture-strip img")) == 5
    retried = _by(browser, "#job-grid td.s-retried")[0]
    ActionChains(browser).move_to_element(retried).perform()
    info = _wait(lambda: "retried" in _by(browser, "#cell-info")[0].text and _by(browser, "#cell-info")[0].text,
                 "the hovered job's details")
    assert "worker node-" in info and "1 attempt" in info and "error: RenderError: Mitsuba ran out of memory" in info
    assert len(_by(browser, "#job-grid td.slow")) == 2
    _screenshot(browser, shots, "03_run_running")

    browser.get(base + "/?limit=5")  # paging: 12 runs, 5 a page, the older ones a click away
    seen = []
    for page in range(3):
        seen += [r.get_attribute("data-run") for r in _by(browser, "#runs-table tbody tr")]
        assert _by(browser, "#runs-count")[0].text.startswith(f"{min(5, 12 - 5 * page)} of 12 runs")
        if page < 2:
            _by(browser, "#next-page")[0].click()
            _wait(lambda: _by(browser, "#runs-table tbody tr")[0].get_attribute("data-run") not in seen,
                  "the next page")
    assert len(seen) == len(set(seen)) == 12 and not _by(browser, "#next-page")

    browser.get(base + "/?sweep=" + ids.sweep_id)
    assert len(_by(browser, "#runs-table tbody tr")) == 6
    _by(browser, "#runs-table a.run-link")[0].click()
    _wait(lambda: _by(browser, "#sweep-link"), "a sweep run's page")
    _by(browser, "#sweep-link")[0].click()
    _wait(lambda: _by(browser, "#results-table"), "the sweep page")
    _wait(lambda: _images_loaded(browser), "the sweep chart")
    assert browser.execute_script("return document.getElementById('sweep-chart').naturalWidth") == 560
    assert len(_by(browser, "#results-table tbody tr")) == 6
    _screenshot(browser, shots, "04_sweep")

    _by(browser, "#results-table a.run-link")[-1].click()
    _wait(lambda: _by(browser, "#frames"), "a done run's frames")
    browser.execute_script("document.getElementById('frames').scrollIntoView()")  # frames load lazily
    _wait(lambda: _images_loaded(browser), "the frames")
    captions = [c.text for c in _by(browser, "#frames figcaption")]
    benign, adversarial = captions[0::2], captions[1::2]
    assert len(benign) == len(adversarial) == 6 and all(c.endswith("trash_bin 0.90 ✓") for c in benign)
    assert adversarial[0] == "adversarial #0: umbrella 0.90 ✗" and "car 0.90 ✗" in adversarial[1]
    assert "adversarial" in _by(browser, "#headline")[0].text
    held_out = _by(browser, "#split-held_out")[0].text  # mifgsm at ε 32 fools all 6 frames, held-out 3 too
    assert held_out == "held-out frames (1): accuracy 100.0 % → 0.0 % · attack success 100.0 %", held_out
    assert _by(browser, "#split-attacked")[0].text.startswith("attacked frames (5): accuracy 100.0 % → 0.0 %")
    assert browser.execute_script("return document.getElementById('chart-metric').naturalWidth") == 560
    assert browser.execute_script("return document.querySelector('#frames img').getBoundingClientRect().width") == 256
    _screenshot(browser, shots, "05_run_done")

    _by(browser, "#nav-workers")[0].click()
    _wait(lambda: _by(browser, "#workers-table"), "the workers page")
    assert "busy" in _by(browser, "#workers-table")[0].text
    _screenshot(browser, shots, "06_workers")
    _no_console_errors(browser)


def _finish_iteration(blobs: Path, run_id: str) -> None:
    """The running run's current iteration completes and the attack steps (through the Store API)."""
    with open_store(None, blobs) as store:
        run = store.get_run(run_id)
        k = run.iteration
        for f in range(run.n_frames):
            store.job_succeeded(run_id, k, f, np.full((2, 2, 3), 0.01, np.float32), 2.0, True, {"total": 0.4})
        record = {"loss_mean": 2.0, "n_ok": run.n_frames, "n_bad": 0, "dropped_frames": [],
                  "grad_norm": 1.0, "step_seconds": 0.01}
        assert store.advance(run_id, k, store.texture(run_id, k), {"t": k + 1}, record)


def test_an_active_run_page_refreshes_itself_and_cancels_with_the_token(site, browser, shots):
    base, ids, blobs = site
    run_id = ids.runs["running"]
    browser.get(f"{base}/runs/{run_id}")
    assert browser.find_element("tag name", "body").get_attribute("data-refresh") == "5"
    marker = browser.execute_script("window.__sameDocument = 1; return window.__sameDocument;")
    _finish_iteration(blobs, run_id)
    _wait(lambda: "iteration 5 of 8" in _by(browser, "#run-progress")[0].text, "the refreshed progress", 30)
    assert browser.execute_script("return window.__sameDocument") == marker  # refreshed in place, not reloaded
    _by(browser, "#token")[0].send_keys("wrong-token-123")
    _by(browser, "#cancel")[0].click()
    _wait(lambda: _by(browser, "#error-line"), "the refusal")
    assert _by(browser, "#error-line")[0].text == "wrong dashboard token"
    _screenshot(browser, shots, "07_wrong_token")
    browser.get(f"{base}/runs/{run_id}")
    _by(browser, "#token")[0].send_keys(TOKEN)
    _by(browser, "#cancel")[0].click()
    _wait(lambda: _by(browser, "h1 .badge") and _by(browser, "h1 .badge")[0].text == "cancelled", "the cancelled run")
    assert _by(browser, "#resume") and not _by(browser, "#cancel")
    _screenshot(browser, shots, "08_cancelled")
    with open_store(None, blobs) as store:
        assert store.get_run(run_id).status == "cancelled"
    browser.get(f"{base}/runs/{ids.runs['done']}")  # the README's screenshot (docs/dashboard_run.png) is this
    _wait(lambda: _by(browser, "#frames"), "the done run's page")
    _screenshot(browser, shots, "09_run_done")
    keep = os.environ.get("UNDREAM_DASHBOARD_SCREENS")  # a folder to copy the screenshots to, for a look
    if keep:
        shutil.copytree(shots.parent, keep, dirs_exist_ok=True)


def test_a_detector_runs_frames_show_its_boxes_crisp_over_the_enlarged_frame(site, browser, shots):
    """A 64-px frame shown at 256 px: the boxes are vectors in the page's pixels laid exactly over the
    picture, in the report's colours (the object's class green, another magenta), each tagged with its
    class and score; the true box dashed. (Runs after the tests that count the farm's runs.)"""
    import io

    from PIL import Image

    from dashboard_data import add_detector_run
    from undream.report.boxes import OBJECT_RGB, OTHER_RGB

    base, _, blobs = site
    with open_store(None, blobs) as store:
        run_id = add_detector_run(store)
    browser.get_log("browser")  # drop what earlier tests left (a refused cancel's 403): this page's own errors count
    browser.get(f"{base}/runs/{run_id}")
    _wait(lambda: _by(browser, "#frames"), "the detector run's frames")
    browser.execute_script("document.getElementById('frames').scrollIntoView()")  # frames load lazily
    _wait(lambda: _images_loaded(browser), "the frames")
    rects = browser.execute_script(
        "return Array.from(document.querySelectorAll('#frames figure')).map(f => [f.querySelector('img'),"
        " f.querySelector('svg.boxes')].map(e => { const r = e.getBoundingClientRect();"
        " return [r.left, r.top, r.width, r.height]; }));")
    assert len(rects) == 4 and all(img == svg and img[2:] == [256, 256] for img, svg in rects), rects
    captions = [c.text for c in _by(browser, "#frames figcaption")]
    assert captions[0].endswith("2 detections, best 0.87, object found ✓") and captions[1].endswith("object missed ✗")
    tags = [t.text for t in _by(browser, "#frames figure.benign svg.boxes text")]
    assert tags[:2] == ["trash bin 0.87", "car 0.31"], tags
    assert "trash bin" in _by(browser, "#boxes-key")[0].text
    benign, adversarial = (np.asarray(Image.open(io.BytesIO(e.screenshot_as_png)).convert("RGB"))[:256, :256]
                           for e in _by(browser, "#frames .pair")[0].find_elements("css selector", "figure"))

    def count(img, rgb):
        return int(np.all(img == rgb, axis=2).sum())
    # the box lines are whole pixels of their colour (crisp, not blended), the tag fills more of them
    assert count(benign, OBJECT_RGB) > 4 * 110 and count(benign, OTHER_RGB) > 2 * 50
    assert count(adversarial, OBJECT_RGB) == 0 and count(adversarial, OTHER_RGB) > 2 * 50
    _screenshot(browser, shots, "10_detector_run")
    _no_console_errors(browser)
