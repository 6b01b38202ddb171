"""Shared fixtures: scene directories of every example, initialised once per session."""
from __future__ import annotations

import fcntl
import os
import shutil
import socket
import subprocess
from pathlib import Path

import pytest

# No network here: Hugging Face must never try the hub (it retries for ~30 s).
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.yaml")) + sorted((ROOT / "examples" / "unreal").glob("*.json"))


# The slow tier: modules that start real workers, browsers, Blender or many CLI subprocesses, or render
# and attack for seconds per test (each over 9 s in all, measured with --durations=0; docs/testing.md).
# `pytest -m "not slow"` leaves them out for the inner loop; CI runs everything.
SLOW_MODULES = {
    "test_farm_integration.py", "test_output_folders.py", "test_deploy_topology.py", "test_stale_runs.py",
    "test_coco_victim.py", "test_farm_cli.py", "test_run_output_rules.py", "test_secrets.py", "test_sim_blender.py",
    "test_scene_cache.py", "test_input_rules.py", "test_settings_edge.py", "test_farm_trust.py",
    "test_fuzz_inputs.py", "test_cli_errors.py", "test_patch_baseline.py", "test_dashboard_browser.py",
    "test_eot.py", "test_blender_import.py", "test_init.py", "test_holdout.py", "test_motion.py",
    "test_coco_nanodet.py", "test_benign_cache.py", "test_full_disk.py",
}


# The longest modules, longest first (each over 100 s of test time in the suite's first run on two
# processes, 2026-11-29, docs/testing.md). Collected first, so that pytest-xdist (--dist loadfile
# --no-loadscope-reorder, pyproject's addopts) hands them out first and the short ones fill the end:
# left in name order, a long module started last kept one process busy while the other sat idle.
LONGEST_FIRST = (
    "test_conditions.py", "test_farm_integration.py", "test_secrets.py", "test_farm_heal.py",
    "test_output_folders.py", "test_run_output_rules.py", "test_stale_runs.py", "test_full_disk.py",
    "test_coco_nanodet.py", "test_coco_victim.py", "test_sim_blender.py", "test_scene_cache.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each module keeps its order


def service_missing(reason: str) -> None:
    """Skip a test whose service (Redis, PostgreSQL) is down; fail instead where
    ``UNDREAM_REQUIRE_SERVICES`` is set (.ci/run sets it), so CI never passes by skipping."""
    if os.environ.get("UNDREAM_REQUIRE_SERVICES"):
        pytest.fail(f"{reason} (UNDREAM_REQUIRE_SERVICES is set)")
    pytest.skip(reason)


@pytest.fixture
def read_only(tmp_path):
    """A read-only tmpfs mounted in tmp_path: as root, chmod would not stop writes (needs root;
    skipped with the reason otherwise)."""
    mount = tmp_path / "ro"
    mount.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(mount)],
                         capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {res.stderr.strip()}")
    yield mount
    subprocess.run(["umount", str(mount)], check=True)


S3_KEY_ID = "undream-test-key"
S3_SECRET = "undream-test-secret-Zq81"  # not a real secret: the tests check it never shows


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="session")
def s3_server():
    """An S3-protocol server for the session (moto's standalone server, in a thread, on 127.0.0.1 and a
    free port): ``{"endpoint", "key_id", "secret"}``; worker subprocesses reach it over HTTP."""
    try:
        from moto.server import ThreadedMotoServer
    except ImportError as exc:
        service_missing(f"moto's S3 server is not installed (pip install 'moto[server]'): {exc}")
    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    yield {"endpoint": f"http://127.0.0.1:{port}", "key_id": S3_KEY_ID, "secret": S3_SECRET}
    server.stop()


def s3_bucket(server: dict, name: str) -> str:
    """Create the bucket ``name`` on ``server`` (``s3_server``); returns its name."""
    import boto3

    client = boto3.client("s3", endpoint_url=server["endpoint"], aws_access_key_id=server["key_id"],
                          aws_secret_access_key=server["secret"], region_name="us-east-1")
    client.create_bucket(Bucket=name)
    client.close()
    return name


@pytest.fixture(scope="session")
def cycles():
    """Blender's Python (for ``sim: blender`` tests): skip, or fail in CI, unless it can import bpy."""
    from undream.errors import UndreamError
    from undream.sim.blender import blender_python, check_blender

    try:
        check_blender()
    except UndreamError as err:
        service_missing(f"Blender's Python is not usable ({err}); {blender_python()}")
    return blender_python()


@pytest.fixture(scope="session")
def mi():
    from undream.variant import mitsuba
    return mitsuba()


@pytest.fixture(scope="session")
def example_scenes(tmp_path_factory, mi) -> dict[str, Path]:
    """Every example in examples/, initialised with 16-spp verification renders (the tests only read
    them). Under pytest-xdist they are written once for the whole run, by the first test process that
    asks, in the folder its processes share; the others wait for it on a lock."""
    from undream.scenedir.init import InitOptions, init_scene
    from undream.settings import load_local

    options = InitOptions(verify_spp=16, cache_dir=load_local().undream_cache)  # asset:NAME examples need the cache
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        base = tmp_path_factory.mktemp("examples")
        return {p.stem: init_scene(p, base / p.stem, options) for p in EXAMPLES}
    run_root = tmp_path_factory.getbasetemp().parent  # this run's pytest-N, above each process's popen-gwK
    base, done = run_root / "examples", run_root / "examples.done"
    with open(run_root / "examples.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(base, ignore_errors=True)  # a process that failed half-way left it
            for p in EXAMPLES:
                init_scene(p, base / p.stem, options)
            done.touch()
    return {p.stem: base / p.stem for p in EXAMPLES}
