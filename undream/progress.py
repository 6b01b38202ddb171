"""One progress bar for every long loop (``tqdm``), each of its steps a point where a stop a signal
asked for ends the loop (:func:`undream.interrupts.check`)."""
from __future__ import annotations

from typing import Any, Iterable, Iterator

from tqdm import tqdm

from undream import interrupts


class _Bar(tqdm):
    """A ``tqdm`` bar that, before each item and each update, raises again a stop whose first
    exception was dropped (a SIGTERM that landed in a ``__del__``): the loop ends there."""

    def __iter__(self) -> Iterator[Any]:
        for item in super().__iter__():
            interrupts.check()
            yield item

    def update(self, n: float | None = 1) -> bool | None:
        interrupts.check()
        return super().update(n)


def progress(items: Iterable[Any] | int, desc: str, unit: str = "it", enabled: bool = True,
             total: int | None = None) -> Any:
    """A ``tqdm`` bar over ``items``, or over ``items`` steps when it is an int
    (advance it with ``.update(1)``, finish with ``.close()``); ``total``: how many ``items``
    a generator will give.

    Disabled, it shows nothing and still iterates, updates and closes.
    """
    if isinstance(items, int):
        return _Bar(total=items, desc=desc, unit=unit, disable=not enabled)
    return _Bar(items, desc=desc, unit=unit, disable=not enabled, total=total)
