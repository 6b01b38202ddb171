"""The pasted-patch baseline: pasted only inside the object's footprint, optimised on attacked frames only."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from farm_support import make_scene, make_victim, run_config, write_yaml
from undream.engine.patch import Footprint, paste

ROOT = Path(__file__).resolve().parents[1]


def _footprint() -> Footprint:
    mask = np.zeros((10, 12), bool)
    mask[2:7, 3:9] = True
    mask[2, 3] = False  # a pixel of the box outside the mask
    return Footprint(0, mask, (3, 2, 9, 7))


def test_paste_changes_only_the_masked_pixels_and_resizes_the_patch_into_the_box():
    image = torch.rand(3, 10, 12)
    patch = torch.rand(3, 4, 4, requires_grad=True)
    foot = _footprint()
    out = paste(image, patch, foot)
    inside = torch.from_numpy(foot.mask)
    assert torch.equal(out[:, ~inside], image[:, ~inside])
    resized = torch.nn.functional.interpolate(patch[None], size=(5, 6), mode="bilinear", align_corners=False)[0]
    np.testing.assert_allclose(out[:, 3, 4].detach(), resized[:, 1, 1].detach(), rtol=1e-6)
    (g,) = torch.autograd.grad(out[:, ~inside].sum(), patch, allow_unused=True)
    assert g is None or not g.any()  # nothing outside the mask depends on the patch


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("patch")
    scene = make_scene(root / "scene", n_frames=4, size=24)
    return {"root": root, "scene": scene, "victim": make_victim(root / "victim")}


def _baseline(tiny, name: str, out: Path, **cfg) -> subprocess.CompletedProcess:
    path = write_yaml(tiny["root"] / f"{name}.yaml", run_config(tiny["scene"], tiny["victim"], name=name, **cfg))
    return subprocess.run([sys.executable, "-m", "undream.cli", "baseline", str(path), "--out", str(out),
                           "--no-progress"], capture_output=True, text=True, cwd=ROOT)


def test_the_baseline_optimises_on_attacked_frames_and_judges_in_the_simulator(tiny, tmp_path):
    out = tmp_path / "base"
    res = _baseline(tiny, "base", out, steps=4)
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "baseline.json").read_text())
    assert results["in_image_space"]["frames"] == [0, 1, 2]  # frame 3 is held out (holdout: auto)
    assert results["victim_evaluations"] == 4 * 3 and len(results["loss_per_step"]) == 4
    assert results["in_simulator"]["held_out"]["frames"] == [3]
    assert set(results["in_simulator"]) == set(results["benign"]) == {"attacked", "held_out"}
    patch = np.load(out / "patch.npy")
    assert patch.shape == (8, 16, 3) and np.abs(patch - 0.5).max() <= 32 / 255 + 1 / 255  # ε = 32 around T0
    assert "in the simulator, held-out frames (1)" in res.stdout


def test_bad_baselines_are_one_line_and_write_nothing(tiny, tmp_path):
    res = _baseline(tiny, "adam", tmp_path / "adam", attack={"name": "adam"})
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "runs PGD" in res.stderr
    assert not (tmp_path / "adam").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    res = _baseline(tiny, "mine", mine)
    assert res.returncode == 2 and "already exists" in res.stderr and (mine / "notes.txt").read_text() == "keep"
