"""The GPU worker's Mitsuba variant: ``cuda_ad_rgb`` first, ``llvm_ad_rgb`` with a log line that says why.

The GPU image (deploy/docker/Dockerfile, target ``gpu``) leaves
``UNDREAM_MI_VARIANT`` unset and relies on :data:`undream.variant.PREFERRED`.
Each end-to-end check runs in a fresh interpreter: a process that set a
variant keeps it, and Dr.Jit initialises its backends once per process.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from farm_support import cuda_driver_present
from undream.variant import PREFERRED, cuda_unusable_reason

ROOT = Path(__file__).resolve().parents[1]
PROBE = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
from undream.settings import load_local
from undream.variant import mitsuba
local = load_local()  # what a worker process and a command do at their start
print(mitsuba(local.mi_variant, libcuda=local.libcuda_path, visible_devices=local.cuda_visible_devices).variant())
"""


def _fresh(env_extra: dict[str, str]) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("UNDREAM_MI_VARIANT", "DRJIT_LIBCUDA_PATH")}
    env.update(env_extra)
    return subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=120)


def test_cuda_comes_first():
    assert PREFERRED == ("cuda_ad_rgb", "llvm_ad_rgb")


def test_without_a_gpu_the_worker_falls_back_to_llvm_and_says_why():
    if cuda_driver_present():
        pytest.skip("this machine has an NVIDIA driver (libcuda.so.1); the fall-back is checked by the next test")
    res = _fresh({})
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "llvm_ad_rgb"
    lines = [ln for ln in res.stderr.splitlines() if "falling back" in ln]
    assert lines == ["INFO undream.variant: falling back to Mitsuba variant llvm_ad_rgb: cuda_ad_rgb failed: "
                     "no NVIDIA driver (libcuda.so.1 cannot be loaded: no GPU here, or a container started "
                     "without the NVIDIA runtime: docker --gpus, a nvidia.com/gpu resource on Kubernetes)"]


def test_a_missing_driver_falls_back_on_any_machine(tmp_path):
    """Dr.Jit's own DRJIT_LIBCUDA_PATH pointed at nothing: no CUDA even where a GPU is present."""
    missing = tmp_path / "libcuda.so.1"
    res = _fresh({"DRJIT_LIBCUDA_PATH": str(missing)})
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "llvm_ad_rgb"
    assert f"cuda_ad_rgb failed: no NVIDIA driver ({missing} cannot be loaded" in res.stderr


def test_a_forced_cuda_variant_fails_with_the_reason_instead_of_falling_back(tmp_path):
    missing = tmp_path / "libcuda.so.1"
    res = _fresh({"DRJIT_LIBCUDA_PATH": str(missing), "UNDREAM_MI_VARIANT": "cuda_ad_rgb"})
    assert res.returncode != 0 and res.stdout == ""
    assert "RenderError: no usable Mitsuba variant (cuda_ad_rgb: no NVIDIA driver" in res.stderr
    assert "falling back" not in res.stderr


class _FakeDriver:
    """A CUDA driver library as ctypes shows it: ``cuInit`` and ``cuDeviceGetCount`` return CUresult."""

    def __init__(self, init: int = 0, devices: int = 1) -> None:
        self.init, self.devices = init, devices

    def cuInit(self, flags: int) -> int:  # noqa: N802 (the driver's name)
        assert flags == 0
        return self.init

    def cuDeviceGetCount(self, count) -> int:  # noqa: N802
        count._obj.value = self.devices
        return 0


def _loader(driver: _FakeDriver | None, optix: bool):
    def load(name: str):
        if name == "libnvoptix.so.1" and optix:
            return object()
        if name != "libnvoptix.so.1" and driver is not None:
            return driver
        raise OSError(f"{name}: cannot open shared object file: No such file or directory")
    return load


DRJIT_ERR = ImportError("jit_init_thread_state(): the CUDA backend hasn't been initialized.")


@pytest.mark.parametrize(("driver", "optix", "expected"), [
    (None, True, "no NVIDIA driver (libcuda.so.1 cannot be loaded"),
    (_FakeDriver(init=100), True, "the NVIDIA driver failed to start (CUDA error 100;"),
    (_FakeDriver(devices=0), True, "no CUDA device visible"),
    (_FakeDriver(), False, "OptiX (libnvoptix.so.1) is missing; in a container set "
                           "NVIDIA_DRIVER_CAPABILITIES=compute,utility,graphics"),
    (_FakeDriver(), True, "jit_init_thread_state(): the CUDA backend hasn't been initialized."),
])
def test_the_reason_names_what_is_missing(driver, optix, expected):
    reason = cuda_unusable_reason(DRJIT_ERR, load=_loader(driver, optix), visible_devices="")
    assert reason.startswith(expected), reason
    if driver is not None and driver.devices == 0:
        assert reason == "no CUDA device visible (CUDA_VISIBLE_DEVICES='')"


def test_the_edge_reads_the_driver_path_and_the_visible_devices():
    """DRJIT_LIBCUDA_PATH and CUDA_VISIBLE_DEVICES are read by undream.settings, then passed down."""
    from undream.settings import load_local

    local = load_local({"DRJIT_LIBCUDA_PATH": "/opt/libcuda.so", "CUDA_VISIBLE_DEVICES": "3"})
    assert (local.libcuda_path, local.cuda_visible_devices) == ("/opt/libcuda.so", "3")
    assert load_local({}).libcuda_path == "libcuda.so.1" and load_local({}).cuda_visible_devices is None
    reason = cuda_unusable_reason(DRJIT_ERR, load=_loader(None, True), libcuda=local.libcuda_path)
    assert reason.startswith("no NVIDIA driver (/opt/libcuda.so cannot be loaded")
