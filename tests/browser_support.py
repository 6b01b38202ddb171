"""Headless Chromium for page tests (undream.report.browser: Debian's ``chromium`` and ``chromium-driver``
through selenium; no Selenium Manager, no network) and a page's measured size. Without Chromium a test
using :func:`chromium` skips saying why, and fails under ``UNDREAM_REQUIRE_SERVICES``."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

from conftest import service_missing
from undream.report import browser
from undream.report.browser import WINDOW, page_size  # noqa: F401  (the tests' names)

MAX_HEIGHT = 6 * WINDOW[1]  # issue 43: a run's page is at most six screen heights tall


def chromium(profile: Path) -> Iterator[Any]:
    """A headless Chromium whose viewport is :data:`WINDOW` (a window of that size holds less, its
    frame included); quit when the generator closes. Skips (or fails) saying what is missing."""
    why = browser.missing()
    if why:
        service_missing(why)
    with browser.chromium(profile) as driver:
        yield driver


def assert_fits(size: dict[str, int]) -> None:
    """The page goal: no horizontal scrolling in the :data:`WINDOW`, at most :data:`MAX_HEIGHT` tall."""
    assert (size["inner_w"], size["inner_h"]) == WINDOW, size
    assert size["scroll_w"] <= size["client_w"], f"horizontal scrolling: {size}"
    assert size["height"] <= MAX_HEIGHT, f"taller than {MAX_HEIGHT} px: {size}"
