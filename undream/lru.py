"""A least-recently-used cache: values by key, at most ``size``, an optional hook for each one dropped.

One class for the process caches that must drop what was used longest ago:
loaded Mitsuba scene groups (``undream.render.scene_cache``), run contexts,
scene caches and victims (``scheduler.contexts``), placed background props
(``undream.scene.background``), texture versions
(``scheduler.stages.run_batch``) and the dashboard's values
(``undream.dashboard.state``); :class:`LastArray` the one-slot case keyed by an array's value.
``functools.lru_cache`` serves the cases whose
key is a function's arguments and whose dropped values need no hook.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Any, Callable, Generic, Hashable, ItemsView, TypeVar

import numpy as np

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class LRU(Generic[K, V]):
    """At most ``size`` values by key. :meth:`put` and :meth:`touch` make a key the most recently
    used; past ``size`` the least recently used is dropped, and every value dropped by
    :meth:`put`, :meth:`drop_oldest` or :meth:`clear` is passed with its key to ``on_evict``
    (e.g. to close it); ``del`` removes a value without the hook. Not thread-safe:
    a caller shared between threads holds its own lock."""

    def __init__(self, size: int, on_evict: Callable[[K, V], Any] | None = None) -> None:
        self.size = size
        self._on_evict = on_evict
        self._items: OrderedDict[K, V] = OrderedDict()

    def __contains__(self, key: object) -> bool:
        """Whether ``key`` is held (does not count as a use)."""
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def touch(self, key: K) -> V:
        """The value of ``key``, now the most recently used; KeyError when it is not held."""
        self._items.move_to_end(key)
        return self._items[key]

    def put(self, key: K, value: V) -> V:
        """Hold ``value`` under ``key`` as the most recently used, then drop the least recently used
        ones past ``size``; returns ``value``."""
        self._items[key] = value
        self._items.move_to_end(key)
        while len(self._items) > self.size:
            self.drop_oldest()
        return value

    def drop_oldest(self) -> None:
        """Drop the least recently used value, through the hook; KeyError when empty."""
        key, value = self._items.popitem(last=False)
        if self._on_evict is not None:
            self._on_evict(key, value)

    def __delitem__(self, key: K) -> None:
        """Remove ``key`` without the hook; KeyError when it is not held."""
        del self._items[key]

    def items(self) -> ItemsView[K, V]:
        """The held (key, value) pairs, least recently used first (does not count as a use)."""
        return self._items.items()

    def clear(self) -> None:
        """Drop every value, least recently used first, each through the hook."""
        while self._items:
            self.drop_oldest()


class LastArray(Generic[V]):
    """What was derived from the last array seen, reused while the next array equals it by value
    (the frames of one iteration share one texture: its linear tensor for the renders,
    ``undream.render.differentiable``, and its sRGB derivative for the gradients,
    ``undream.engine.gradient``, are each computed once). Holds a copy of that array."""

    def __init__(self) -> None:
        self._held: tuple[Any, V] | None = None

    def get(self, array: Any, derive: Callable[[Any], V]) -> V:
        """``derive(array)``, or the value derived from the last array when ``array`` equals it."""
        if self._held is None or self._held[0].shape != array.shape or not np.array_equal(self._held[0], array):
            self._held = (np.array(array, copy=True), derive(array))
        return self._held[1]

    def clear(self) -> None:
        self._held = None
