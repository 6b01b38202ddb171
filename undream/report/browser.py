"""A report page in headless Chromium: its measured size and screenshots (no network, no script of ours).

Debian's ``chromium`` and ``chromium-driver`` driven through selenium (the
``test`` extra; no Selenium Manager, nothing downloaded). The viewport is
:data:`WINDOW` CSS px at a device scale of 1, so a screenshot's pixels are
CSS pixels. Used by ``scripts/report_screenshots.py`` and the page tests
(tests/browser_support.py).
"""
from __future__ import annotations

import base64
import contextlib
import os
import time
from pathlib import Path
from typing import Any, Iterator

from undream.errors import UndreamError

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
WINDOW = (1400, 900)  # CSS px: the viewport the page goals are measured in
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run")
LOAD_SECONDS = 30  # a page still loading after this long is an error


class BrowserError(UndreamError):
    """Chromium, its driver or selenium is missing, or a page did not load."""


def missing() -> str | None:
    """Why no page can be opened here (one sentence), None when Chromium, its driver and selenium are there."""
    absent = [p for p in (CHROMIUM, CHROMEDRIVER) if not os.access(p, os.X_OK)]
    if absent:
        return f"{' and '.join(absent)} missing (apt-get install chromium chromium-driver; deploy/setup.sh does)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium not installed (pip install 'undream[test]')"
    return None


@contextlib.contextmanager
def chromium(profile: Path, window: tuple[int, int] = WINDOW) -> Iterator[Any]:
    """A headless Chromium (selenium WebDriver) whose viewport is ``window`` CSS px (a window of that
    size holds less, its frame included), profile in ``profile``; quit on leaving. BrowserError
    saying what is missing when it cannot start."""
    why = missing()
    if why:
        raise BrowserError(why)
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError as err:  # checked by missing(); here for the type checker's sake
        raise BrowserError(f"selenium: {err}") from None
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        driver.set_page_load_timeout(60)
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                               {"width": window[0], "height": window[1], "deviceScaleFactor": 1, "mobile": False})
        yield driver
    finally:
        driver.quit()


def load(driver: Any, url: str) -> None:
    """Open ``url`` and wait until the document has loaded (BrowserError after :data:`LOAD_SECONDS`)."""
    driver.get(url)
    end = time.monotonic() + LOAD_SECONDS
    while driver.execute_script("return document.readyState;") != "complete":
        if time.monotonic() > end:
            raise BrowserError(f"{url}: still loading after {LOAD_SECONDS} s")
        time.sleep(0.1)


def page_size(driver: Any, url: str) -> dict[str, int]:
    """Load ``url`` and measure it: the document's scroll width and height (``scroll_w``, ``height``),
    the viewport's width without its scroll bar (``client_w``) and the window's (``inner_w``,
    ``inner_h``). Thumbnails load lazily; their width and height attributes hold their place."""
    load(driver, url)
    return driver.execute_script(
        "const e = document.documentElement; return {scroll_w: e.scrollWidth, client_w: e.clientWidth, "
        "height: e.scrollHeight, inner_w: window.innerWidth, inner_h: window.innerHeight};")


def top_png(driver: Any, url: str) -> bytes:
    """PNG bytes of the top of the page at ``url``: what the viewport shows on opening it."""
    load(driver, url)
    return driver.get_screenshot_as_png()


def full_png(driver: Any, url: str) -> bytes:
    """PNG bytes of the whole page at ``url`` at full size (the viewport's width, the page's height),
    captured beyond the viewport through the DevTools protocol; lazy images below the fold included."""
    load(driver, url)
    for img in driver.find_elements("css selector", "img[loading=lazy]"):
        driver.execute_script("arguments[0].loading = 'eager';", img)
    driver.execute_script("return Promise.all(Array.from(document.images).filter(i => !i.complete)"
                          ".map(i => new Promise(r => { i.onload = i.onerror = r; })));")
    size = driver.execute_script("const e = document.documentElement; return [e.scrollWidth, e.scrollHeight];")
    shot = driver.execute_cdp_cmd("Page.captureScreenshot", {
        "format": "png", "captureBeyondViewport": True,
        "clip": {"x": 0, "y": 0, "width": size[0], "height": size[1], "scale": 1}})
    return base64.b64decode(shot["data"])
