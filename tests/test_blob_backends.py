"""One blob interface, every backend: a folder, the run database (SQLite, PostgreSQL), S3 (moto's server).

Each test runs against every backend through the same :class:`undream.store.BlobStore`
interface, on its own keys (``runs/<uuid>``) of a store opened once per backend.
"""
from __future__ import annotations

import datetime as dt
import re
import time
import uuid

import numpy as np
import pytest

from conftest import s3_bucket
from farm_support import fresh_postgres
from undream.errors import StoreError
from undream.store import BlobOptions, open_store, parse_blob_url
from undream.store.blob_backends import BlobInfo

BACKENDS = ["folder", "database-sqlite", "database-postgresql", "s3"]


@pytest.fixture(scope="module", params=BACKENDS)
def store(request, tmp_path_factory):
    """A store whose blobs live in the backend ``request.param``."""
    root = tmp_path_factory.mktemp(request.param)
    drop = None
    if request.param == "folder":
        s = open_store(None, root / "blobs")
    elif request.param == "database-sqlite":
        s = open_store(f"sqlite:///{root / 'runs.db'}", "database", options=BlobOptions(local_dir=str(root / "local")))
    elif request.param == "database-postgresql":
        url, drop = fresh_postgres()
        s = open_store(url, "database")
    else:
        server = request.getfixturevalue("s3_server")
        bucket = s3_bucket(server, f"contract-{uuid.uuid4().hex[:8]}")
        s = open_store(f"sqlite:///{root / 'runs.db'}", f"s3://{bucket}/farm/blobs",
                       options=s3_options(server, local_dir=str(root / "local")))
    yield s
    s.close()
    if drop is not None:
        drop()


def s3_options(server: dict, **more) -> BlobOptions:
    return BlobOptions(s3_endpoint_url=server["endpoint"], s3_region="us-east-1",
                       s3_access_key_id=server["key_id"], s3_secret_access_key=server["secret"], **more)


@pytest.fixture
def ns() -> str:
    return f"runs/{uuid.uuid4().hex[:12]}"


def test_round_trips_and_idempotent_writes(store, ns):
    blobs = store.blobs
    arr = np.arange(24, dtype=np.float32).reshape(2, 4, 3)
    key = blobs.put_array(f"{ns}/texture/000001.npy", arr)
    assert blobs.put_array(key, arr) == key  # the same write again: one blob, same bytes
    assert np.array_equal(blobs.get_array(key), arr) and blobs.get_array(key).dtype == np.float32
    blobs.put_array(key, arr + 1)  # a new content replaces the old one whole
    assert np.array_equal(blobs.get_array(key), arr + 1)
    blobs.put_json(f"{ns}/state.json", {"m": [1, 2], "x": None})
    blobs.put_json(f"{ns}/state.json", {"m": [1, 2], "x": None})
    assert blobs.get_json(f"{ns}/state.json") == {"m": [1, 2], "x": None}
    assert [i.key for i in blobs.listing(ns)] == [f"{ns}/state.json", key]
    assert blobs.size(key) == len(blobs.get_bytes(key)) and blobs.exists(key)
    assert blobs.usage(ns) == (2, blobs.size(key) + blobs.size(f"{ns}/state.json"))


def test_missing_keys_are_one_line_errors_naming_the_key(store, ns):
    blobs = store.blobs
    key = f"{ns}/texture/000009.npy"
    assert not blobs.exists(key)
    for read in (blobs.get_array, blobs.get_file, blobs.size, blobs.get_bytes):
        with pytest.raises(StoreError) as info:
            read(key)
        assert f"blob {key!r}: not found in the " in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(StoreError, match=re.escape(f"blob '{ns}/x.json': not found")):
        blobs.get_json(f"{ns}/x.json")


@pytest.mark.parametrize("key", ["../escape.npy", "/etc/passwd.npy", "runs//x.npy", ".hidden.npy"])
def test_bad_keys_are_refused_before_the_backend(store, key):
    with pytest.raises(StoreError, match=re.escape(f"blob key {key!r}")):
        store.blobs.put_array(key, np.zeros(3))
    with pytest.raises(StoreError, match=re.escape(f"blob key {key!r}")):
        store.blobs.exists(key)


def test_delete_prefix_deletes_the_prefix_and_nothing_beside_it(store, ns):
    blobs = store.blobs
    keep = [f"{ns}_b/a.npy", f"{ns}0/a.npy", f"{ns}x/a.npy"]  # '_' is no wildcard, 'ns0' not under 'ns'
    gone = [f"{ns}/grad/000000/0000.npy", f"{ns}/grad/000000/0001.npy", f"{ns}/grad/000001/0000.npy"]
    for key in keep + gone:
        blobs.put_array(key, np.ones(2))
    assert blobs.delete_prefix(f"{ns}/grad/000000") == 2
    assert [i.key for i in blobs.listing(f"{ns}/grad")] == [gone[2]]
    assert blobs.delete_prefix(gone[2]) == 1 and blobs.delete_prefix(f"{ns}/grad") == 0
    assert all(blobs.exists(k) for k in keep)
    blobs.delete(keep + [f"{ns}/never.npy"])
    assert not any(blobs.exists(k) for k in keep)


def test_get_file_gives_a_local_file_on_every_backend(store, ns, tmp_path):
    src = tmp_path / "scene.tar"
    src.write_bytes(b"packed scene " * 1000)
    key = store.blobs.put_file(f"{ns}/scene.tar", src)
    local = store.blobs.get_file(key)
    assert local.is_file() and local.read_bytes() == src.read_bytes()
    with store.blobs.open(key) as f:
        assert f.read() == src.read_bytes()
    if store.blobs.root is None:  # a copy, refreshed on each call
        assert store.blobs.local_dir in local.parents
        src.write_bytes(b"new")
        store.blobs.put_file(key, src)
        assert store.blobs.get_file(key).read_bytes() == b"new"


def test_touch_renews_the_last_use(store, ns):
    blobs = store.blobs
    a, b = f"{ns}/a.json", f"{ns}/b.json"
    blobs.put_json(a, "a")
    blobs.put_json(b, "b")
    before = {i.key: i.used for i in blobs.listing(ns)}
    assert all(isinstance(i, BlobInfo) and i.used.tzinfo is not None for i in blobs.listing(ns))
    later = dt.datetime.now(dt.timezone.utc)
    time.sleep(1.1 if store.blobs.where.startswith("S3") else 0.05)  # S3 keeps whole seconds
    blobs.touch(a)
    after = {i.key: i.used for i in blobs.listing(ns)}
    assert after[a] > before[a] and after[a] >= later.replace(microsecond=0) and after[b] == before[b]
    blobs.touch(f"{ns}/gone.json")  # nothing there: no error


def test_a_run_advances_with_its_blobs_in_the_backend(store):
    """The store's own writes (create, start, advance in one transaction) on each backend."""
    tex = np.full((4, 5, 3), 0.25, np.float32)
    run = store.create_run("blobs", {"attack": {}}, n_frames=2, seed=1, texture0=tex,
                           attack_state0={"t": 0}, arrays0={"T0": tex})
    assert store.advance(run, 0, tex + 0.25, {"t": 1}, {"loss_mean": 0.5}, arrays={"T0": tex})
    assert not store.advance(run, 0, tex, {"t": 9}, {"loss_mean": 0.1})  # the compare-and-set holds
    assert np.array_equal(store.texture(run, 1), tex + 0.25) and store.attack_state(run, 1)["t"] == 1
    assert np.array_equal(store.attack_state(run, 1)["T0"], tex)
    store.delete_run(run)
    assert store.blobs.listing(f"runs/{run}") == []


def test_check_writable_and_where(store):
    store.blobs.check_writable()
    assert "undream-test-secret" not in repr(store) and "undream-test-secret" not in store.blobs.where


def test_s3_errors_name_the_key_and_hide_the_secret(s3_server, tmp_path):
    bucket = s3_bucket(s3_server, f"secret-{uuid.uuid4().hex[:8]}")
    opts = BlobOptions(s3_endpoint_url=s3_server["endpoint"].replace("127.0.0.1", "user:pw@127.0.0.1"),
                       s3_region="us-east-1", s3_access_key_id="AKIDEXAMPLE", s3_secret_access_key="hunter2-secret")
    with open_store(f"sqlite:///{tmp_path / 'r.db'}", f"s3://{bucket}/p", options=opts) as s:
        assert "hunter2" not in repr(s) and "pw@" not in s.blobs.where and "AKIDEXAMPLE" not in repr(opts)
    missing = BlobOptions(**{**s3_options(s3_server).__dict__})
    with open_store(f"sqlite:///{tmp_path / 'r.db'}", "s3://no-such-bucket-here/p", options=missing) as s:
        with pytest.raises(StoreError) as info:
            s.blobs.check_writable()
        message = str(info.value)
        assert "s3://no-such-bucket-here/p" in message and "create the bucket" in message
        assert s3_server["secret"] not in message and "\n" not in message


@pytest.mark.parametrize("url, kind", [("database", "database"), ("s3://my-bucket/a/b", "s3"),
                                       ("/srv/blobs", "folder"), ("file:///srv/blobs", "folder")])
def test_blob_urls(url, kind):
    assert parse_blob_url(url).kind == kind


@pytest.mark.parametrize("url, message", [
    ("s3://key:hunter2@my-bucket/p", "give only s3://bucket/prefix"),
    ("s3://A_Bucket/p", "is not a bucket name"),
    ("gs://u:hunter2@bucket/p", "unsupported scheme 'gs'"),
    ("s3://my-bucket/../p", "invalid segment"),
])
def test_bad_blob_urls_are_one_line_errors(url, message):
    with pytest.raises(StoreError, match=re.escape(message)) as info:
        parse_blob_url(url)
    assert "hunter2" not in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("blob_url", ["database", "s3://my-bucket/p"])
def test_no_database_url_with_blobs_outside_a_folder_names_the_setting(blob_url):
    with pytest.raises(StoreError, match=r"^database_url: not set, and blob_url .* set database_url"):
        open_store(None, blob_url)


class _FakeTransport:
    """What the shelf stores: anything with ``save(path)`` (a real one needs a scene and a capture)."""

    def __init__(self, size: int) -> None:
        self.size = size

    def save(self, f) -> None:  # the shelf writes into memory (Transport.save takes a file object)
        f.write(b"t" * self.size)


def test_the_transport_cache_keeps_the_most_recently_used_under_its_cap(store, monkeypatch):
    import scheduler.transports as transports
    import undream.render.transport as transport
    from scheduler.transports import BlobTransportShelf, prune_transports

    monkeypatch.setattr(transports, "TOUCH_EVERY_S", 0.0)  # a hit marks its blob used at once
    store.blobs.delete_prefix("transports")
    shelf = BlobTransportShelf(store.blobs, "scenes/abc.tar", cap_bytes=10_000)
    for name in ("k1", "k2", "k3", "k4"):
        shelf.put(name, _FakeTransport(3000))  # the 4th write passes the cap: k1, the oldest, goes
    assert shelf.evicted == 1 and not store.blobs.exists("transports/abc/k1.npz")
    time.sleep(1.1 if store.blobs.where.startswith("S3") else 0.05)  # S3 keeps whole seconds
    monkeypatch.setattr(transport.Transport, "load", classmethod(lambda cls, f: f.read()))
    assert shelf.get("k2") == b"t" * 3000 and shelf.hits == 1  # a hit marks k2 used
    assert shelf.get("k1") is None and shelf.misses == 1
    assert prune_transports(store.blobs, 6000) == 1  # k3, now the least recently used
    assert [i.key for i in store.blobs.listing("transports")] == ["transports/abc/k2.npz", "transports/abc/k4.npz"]
    assert prune_transports(store.blobs, 0) == 2 and store.blobs.listing("transports") == []
