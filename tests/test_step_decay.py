"""attack.step_decay: PGD's and MI-FGSM's step size over the iterations (docs/runs.md, "Lamps at night")."""
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
from undream.errors import SpecError
from undream.spec.attack import AttackConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["pgd", "mifgsm"])
def test_cosine_steps_shrink_from_the_step_size_to_nearly_nothing(name):
    """A gradient that always points up: each step moves every texel by that iteration's step size,
    the configured one throughout without decay, and step_size·(1 + cos(π·k/N))/2 with cosine."""
    moves = {}
    for decay in ("none", "cosine"):
        attack = make_attack(AttackConfig(name=name, eps=255, steps=4, step_size=40, step_decay=decay))
        T, state = attack.start(torch.full((2, 2, 3), 0.1))
        seen = []
        for _ in range(4):
            T_next, state = attack.step(T, torch.ones_like(T), 1.0, state)
            seen.append(float((T_next - T).max()) * 255)
            T = T_next
        moves[decay] = seen
    assert moves["none"] == pytest.approx([40.0] * 4, abs=1e-3)
    assert moves["cosine"] == pytest.approx([40 * (1 + math.cos(math.pi * k / 4)) / 2 for k in range(4)], abs=1e-3)
    assert moves["cosine"][-1] < 6  # the last step: 5.9 of 255 levels


def test_a_bad_step_decay_is_refused_naming_the_field():
    assert AttackConfig().step_decay == "none"
    assert AttackConfig.from_dict(AttackConfig(step_decay="cosine").to_dict()).step_decay == "cosine"
    with pytest.raises(SpecError, match=r"^attack\.step_decay: must be one of none, cosine, got 'linear'"):
        AttackConfig(step_decay="linear")
    for name in ("apgd", "adam"):  # they set their own step sizes: a decay would be silently ignored
        with pytest.raises(SpecError, match=rf"^attack\.step_decay: {name} sets its own step sizes"):
            AttackConfig(name=name, step_decay="cosine")


def test_undream_run_decays_its_steps_as_the_config_says(tmp_path):
    """Through `undream run`: the stored config keeps the field, and it changes the attack's steps
    (the same seed and frames, only the step sizes differ); a bad value is one line, nothing written."""
    scene = make_scene(tmp_path / "scene", n_frames=4, size=16)
    victim = make_victim(tmp_path / "victim")
    textures = runs_per_attack_value(tmp_path, scene, victim, "step_decay", ("none", "cosine"))
    assert not np.array_equal(textures["none"], textures["cosine"])
    bad = run_config(scene, victim, name="d_bad", steps=3, attack={"name": "apgd", "step_decay": "cosine"})
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(tmp_path / "bad.yaml", bad)),
                          "--out", str(tmp_path / "bad")], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "attack.step_decay: apgd sets its own step sizes" in res.stderr
    assert not (tmp_path / "bad").exists()
