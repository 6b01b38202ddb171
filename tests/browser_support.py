"""Headless Chromium for page tests (Debian's ``chromium`` and ``chromium-driver`` through selenium; no
Selenium Manager, no network) and a page's measured size. Without Chromium a test using
:func:`chromium` skips saying why, and fails under ``UNDREAM_REQUIRE_SERVICES``."""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Iterator

import pytest

from conftest import service_missing

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
WINDOW = (1400, 900)  # CSS px: the viewport the page goals are measured in
MAX_HEIGHT = 6 * WINDOW[1]  # issue 43: a run's page is at most six screen heights tall


def chromium(profile: Path) -> Iterator[Any]:
    """A headless Chromium whose viewport is :data:`WINDOW` (a window of that size holds less, its
    frame included); quit when the generator closes."""
    missing = [p for p in (CHROMIUM, CHROMEDRIVER) if not os.access(p, os.X_OK)]
    if missing:
        service_missing(f"{' and '.join(missing)} missing (apt-get install chromium chromium-driver; "
                        "deploy/setup.sh does)")
    pytest.importorskip("selenium", reason="selenium not installed (pip install 'undream[test]')")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(60)
    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                           {"width": WINDOW[0], "height": WINDOW[1], "deviceScaleFactor": 1, "mobile": False})
    try:
        yield driver
    finally:
        driver.quit()


def page_size(driver: Any, url: str) -> dict[str, int]:
    """Load ``url`` and measure it: the document's scroll width and height (``scroll_w``, ``height``),
    the viewport's width without its scroll bar (``client_w``) and the window's (``inner_w``,
    ``inner_h``). Thumbnails load lazily; their width and height attributes hold their place."""
    driver.get(url)
    end = time.monotonic() + 30
    while driver.execute_script("return document.readyState;") != "complete":
        assert time.monotonic() < end, f"{url}: still loading after 30 s"
        time.sleep(0.1)
    return driver.execute_script(
        "const e = document.documentElement; return {scroll_w: e.scrollWidth, client_w: e.clientWidth, "
        "height: e.scrollHeight, inner_w: window.innerWidth, inner_h: window.innerHeight};")


def assert_fits(size: dict[str, int]) -> None:
    """The page goal: no horizontal scrolling in the :data:`WINDOW`, at most :data:`MAX_HEIGHT` tall."""
    assert (size["inner_w"], size["inner_h"]) == WINDOW, size
    assert size["scroll_w"] <= size["client_w"], f"horizontal scrolling: {size}"
    assert size["height"] <= MAX_HEIGHT, f"taller than {MAX_HEIGHT} px: {size}"
