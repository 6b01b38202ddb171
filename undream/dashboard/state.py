"""What the dashboard's views share: the settings, the store (opened lazily) and a cache."""
from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Any, Callable

from undream.dashboard.errors import Unavailable
from undream.dashboard.grid import job_grid
from undream.dashboard.query import ACTIVE_STATUSES
from undream.errors import StoreError
from undream.lru import LRU

if TYPE_CHECKING:
    from undream.settings import Settings
    from undream.store import JobLine, Store

EXTENSION = "undream"  # the key of the app's Farm in ``app.extensions``
CACHE_ITEMS = 2048  # values kept in memory (PNGs, masks, rows of finished runs), least recently used dropped


class Cache:
    """Values by key (PNG bytes, masks, finished runs' rows); a key names the run's state, so a run
    that changes makes new keys. Least recently used entries go first."""

    def __init__(self, size: int = CACHE_ITEMS) -> None:
        self._items: LRU[tuple[Any, ...], Any] = LRU(size)
        self._lock = threading.Lock()

    def get(self, key: tuple[Any, ...], make: Callable[[], Any]) -> Any:
        with self._lock:
            if key in self._items:
                return self._items.touch(key)
        data = make()
        with self._lock:
            return self._items.put(key, data)


class Farm:
    """What the views share: the settings, the store (opened lazily) and the cache."""

    def __init__(self, settings: "Settings", opener: Callable[[str | None, str], "Store"]) -> None:
        self.settings = settings
        self.cache = Cache()
        self._opener = opener
        self._store: "Store | None" = None
        self._lock = threading.Lock()

    def store(self) -> "Store":
        """The store; :class:`Unavailable` (one line) while the database cannot be opened."""
        with self._lock:
            if self._store is None:
                try:
                    self._store = self._opener(self.settings.database_url, self.settings.blob_url)
                except StoreError as err:  # the cause tells /api/health "no farm database yet" apart
                    raise Unavailable(" ".join(str(err).split())) from err
            return self._store

    def attack_jobs(self, run_id: str) -> list["JobLine"]:
        """The run's attack jobs (the grid and the accuracy chart read them), cached once the run has
        finished: its jobs no longer change until it is resumed, which changes ``updated``."""
        store = self.store()
        run = store.get_run(run_id)
        if run.status in ACTIVE_STATUSES:
            return store.job_lines(run_id)
        return self.cache.get(("attack-jobs", run_id, run.updated, run.status), lambda: store.job_lines(run_id))

    def grid(self, run_id: str) -> dict[str, Any]:
        """The run's job grid (:func:`undream.dashboard.grid.job_grid`), cached once the run has finished."""
        store = self.store()
        run = store.get_run(run_id)
        if run.status in ACTIVE_STATUSES:
            return job_grid(store, run_id)
        return self.cache.get(("grid", run_id, run.updated, run.status),
                              lambda: job_grid(store, run_id, self.attack_jobs(run_id)))

    def close(self) -> None:
        with self._lock:
            if self._store is not None:
                self._store.close()
                self._store = None


def farm() -> Farm:
    """The current app's :class:`Farm`."""
    from flask import current_app

    return current_app.extensions[EXTENSION]
