"""The one atomic file write (undream.spec.io.atomic_write) and the one LRU cache (undream.lru.LRU)."""
from __future__ import annotations

import pytest

from undream.lru import LRU
from undream.spec.io import atomic_write


def test_an_interrupted_write_leaves_the_old_file_and_no_temporary_file(tmp_path):
    target = tmp_path / "results.json"
    target.write_text('{"old": true}')

    def dies(f):
        f.write(b'{"new": ')
        raise KeyboardInterrupt  # not only OSError: whatever stops the writer

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, dies)
    assert target.read_text() == '{"old": true}'
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]

    assert atomic_write(target, "ü\n") == 3  # text as UTF-8; the bytes written
    assert target.read_bytes() == "ü\n".encode()
    atomic_write(target, b"\x00\x01", mode=0o600)
    assert target.read_bytes() == b"\x00\x01" and target.stat().st_mode & 0o777 == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_the_lru_drops_the_least_recently_used_through_its_hook():
    dropped: list[tuple[str, int]] = []
    cache: LRU[str, int] = LRU(2, on_evict=lambda k, v: dropped.append((k, v)))
    cache.put("a", 1)
    cache.put("b", 2)
    assert cache.touch("a") == 1  # now "b" is the least recently used
    assert "b" in cache and cache.put("c", 3) == 3
    assert dropped == [("b", 2)] and "b" not in cache and len(cache) == 2
    del cache["a"]  # removed, not dropped: no hook
    assert dropped == [("b", 2)]
    cache.put("d", 4)
    cache.clear()  # every value through the hook, least recently used first
    assert dropped == [("b", 2), ("c", 3), ("d", 4)] and len(cache) == 0
    with pytest.raises(KeyError):
        cache.touch("a")


def test_last_array_derives_once_per_value_and_again_when_it_changes():
    """The render's linear texture and the gradient's sRGB derivative share this one-slot cache:
    reused while the texture is equal by value, derived again when a texel or the shape changes,
    and never fooled by the caller changing the array it passed in."""
    import numpy as np

    from undream.lru import LastArray

    calls = []
    last: LastArray[float] = LastArray()
    derive = lambda a: calls.append(a.copy()) or float(a.sum())  # noqa: E731
    t = np.ones((2, 3), np.float32)
    assert last.get(t, derive) == 6.0 and last.get(t.copy(), derive) == 6.0 and len(calls) == 1
    t[0, 0] = 2.0  # changed in place: not the array held
    assert last.get(t, derive) == 7.0 and len(calls) == 2
    assert last.get(np.ones((3, 2), np.float32), derive) == 6.0 and len(calls) == 3
    last.clear()
    assert last.get(np.ones((3, 2), np.float32), derive) == 6.0 and len(calls) == 4
