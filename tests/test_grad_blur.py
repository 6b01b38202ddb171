"""attack.grad_blur: each iteration's texture gradient smoothed by a Gaussian before the attack's step
(docs/runs.md, "Smoothed gradients")."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from farm_support import make_scene, make_victim, run_config, runs_per_attack_value, write_yaml
from undream.attacks import make_attack
from undream.attacks.base import blur_gradient
from undream.errors import SpecError
from undream.spec.attack import AttackConfig

ROOT = Path(__file__).resolve().parents[1]


def test_blur_spreads_a_point_as_a_gaussian_and_keeps_a_constant():
    G = torch.zeros(21, 21, 3, dtype=torch.float64)
    G[10, 10, 1] = 1.0
    out = blur_gradient(G, 2.0)
    assert float(out.sum()) == pytest.approx(1.0)  # nothing lost away from the edges
    assert float(out[..., 0].abs().max()) == 0 and float(out[..., 2].abs().max()) == 0  # channels apart
    weights = torch.tensor([math.exp(-0.5 * (d / 2.0) ** 2) for d in range(-6, 7)], dtype=torch.float64)
    weights = weights / weights.sum()
    assert torch.allclose(out[4:17, 4:17, 1], torch.outer(weights, weights))
    assert float(out[10, 10, 1]) < 0.05 and float(out[10, 13, 1]) > 0.01  # spread over its neighbours
    constant = torch.full((8, 5, 3), 0.25)
    assert torch.allclose(blur_gradient(constant, 3.0), constant)  # replicated edges: no darkening
    assert blur_gradient(G, 0.0) is G


@pytest.mark.parametrize("name", ["pgd", "apgd", "mifgsm", "adam"])
def test_every_attack_steps_along_the_smoothed_gradient(name):
    """A gradient of independent noise: without blur PGD's sign step flips from texel to texel; with
    σ = 2 texels neighbours move together (the texture's change is smooth), for every attack alike.
    Texels no frame sees still keep their value."""
    gen = torch.Generator().manual_seed(0)
    G = torch.randn(32, 32, 3, generator=gen)
    G[:, :4] = 0  # never seen
    changes = {}
    for blur in (0.0, 2.0):
        attack = make_attack(AttackConfig(name=name, eps=16, steps=10, grad_blur=blur))
        T0 = torch.full((32, 32, 3), 0.5)
        T, state = attack.start(T0, visible=torch.zeros(32, 32, dtype=torch.bool))
        T_next, _ = attack.step(T, G, 1.0, state)
        assert torch.equal(T_next[:, :4], T0[:, :4])
        changes[blur] = (T_next - T)[:, 4:]
    def roughness(d):  # mean difference between horizontal neighbours against the change's own size
        return float((d[:, 1:] - d[:, :-1]).abs().mean() / d.abs().mean())
    assert roughness(changes[0.0]) > 0.9
    assert roughness(changes[2.0]) < 0.5


def test_a_bad_grad_blur_is_refused_naming_the_field():
    assert AttackConfig().grad_blur == 0.0
    assert AttackConfig.from_dict(AttackConfig(grad_blur=1.5).to_dict()).grad_blur == 1.5
    for bad in (-1, 65, float("nan"), "2"):
        with pytest.raises(SpecError, match=r"^attack\.grad_blur: "):
            AttackConfig(grad_blur=bad)


def test_undream_run_smooths_its_steps_as_the_config_says(tmp_path):
    """Through `undream run`: the stored config keeps the field, and with σ = 2 texels neighbouring texels
    the attack moved move the same way far more often than without (the same seed and frames); a bad
    value is one line, nothing written."""
    scene = make_scene(tmp_path / "scene", n_frames=4, size=16)
    victim = make_victim(tmp_path / "victim")
    textures = runs_per_attack_value(tmp_path, scene, victim, "grad_blur", (0, 2))  # whole numbers: run names
    def opposed(texture):  # of the neighbouring pairs of moved texels, the share moved opposite ways
        sign = np.sign(np.round((texture.astype(np.float64) - 128 / 255) * 255))  # the scene's grey, 8-bit
        pairs = [(sign[:, 1:], sign[:, :-1]), (sign[1:], sign[:-1])]
        moved = sum(int(((a != 0) & (b != 0)).sum()) for a, b in pairs)
        assert moved > 20  # the attack moved the texture
        return sum(int((a * b < 0).sum()) for a, b in pairs) / moved
    assert opposed(textures[0]) > 0.05
    assert opposed(textures[2]) < 0.5 * opposed(textures[0])
    bad = run_config(scene, victim, name="b_bad", steps=3, attack={"grad_blur": -1})
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(tmp_path / "bad.yaml", bad)),
                          "--out", str(tmp_path / "bad")], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "attack.grad_blur: -1 is out of range" in res.stderr
    assert not (tmp_path / "bad").exists()
