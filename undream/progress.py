"""One progress bar for every long loop (``tqdm``, imported on first use)."""
from __future__ import annotations

from typing import Any, Iterable

from tqdm import tqdm


def progress(items: Iterable[Any] | int, desc: str, unit: str = "it", enabled: bool = True,
             total: int | None = None) -> Any:
    """A ``tqdm`` bar over ``items``, or over ``items`` steps when it is an int
    (advance it with ``.update(1)``, finish with ``.close()``); ``total``: how many ``items``
    a generator will give.

    Disabled, it shows nothing and still iterates, updates and closes.
    """
    if isinstance(items, int):
        return tqdm(total=items, desc=desc, unit=unit, disable=not enabled)
    return tqdm(items, desc=desc, unit=unit, disable=not enabled, total=total)
