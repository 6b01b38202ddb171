"""attack.frame_weights: how an iteration's frame gradients are combined (docs/runs.md, "Lamps at night")."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from farm_support import make_scene, make_victim, runs_per_attack_value
from undream.attacks import AttackError, average_frames
from undream.errors import SpecError
from undream.spec.attack import AttackConfig


def test_unit_weights_give_a_dim_frame_the_pull_of_a_bright_one():
    """Two frames that want opposite texels, one with 100× the gradient (a sunlit view beside a
    back-lit one): the mean follows the bright frame alone, unit weights both alike."""
    dim, bright = torch.zeros(2, 2, 3), torch.zeros(2, 2, 3)
    dim[0, 0, 0], bright[1, 1, 2] = 1.0, 100.0
    nan = torch.full((2, 2, 3), float("nan"))
    zero = torch.zeros(2, 2, 3)
    G, loss, kept = average_frames([dim, bright, nan], [1.0, 3.0, 2.0])
    assert kept == [0, 1] and loss == 2.0 and G[0, 0, 0] / G[1, 1, 2] == pytest.approx(0.01)
    G, loss, kept = average_frames([dim, bright, nan, zero], [1.0, 3.0, 2.0, 5.0], weights="unit")
    assert kept == [0, 1, 3] and loss == 3.0
    mean_norm = (1.0 + 100.0 + 0.0) / 3
    assert G[0, 0, 0] == pytest.approx(mean_norm / 3) and G[1, 1, 2] == pytest.approx(mean_norm / 3)
    assert G.count_nonzero() == 2  # the zero frame (the object out of sight) adds nothing
    with pytest.raises(AttackError, match="weights must be 'mean' or 'unit', got 'median'"):
        average_frames([dim], [1.0], weights="median")


def test_a_bad_frame_weights_is_refused_naming_the_field():
    assert AttackConfig().frame_weights == "mean"
    assert AttackConfig.from_dict(AttackConfig(frame_weights="unit").to_dict()).frame_weights == "unit"
    with pytest.raises(SpecError, match=r"^attack\.frame_weights: must be one of mean, unit, got 'median'"):
        AttackConfig(frame_weights="median")


def test_undream_run_combines_the_frames_as_the_config_says(tmp_path):
    """Through `undream run`: the stored config keeps the field, and it changes the attack's steps
    (the same seed and frames, only the weighting differs)."""
    scene = make_scene(tmp_path / "scene", n_frames=4, size=16)
    victim = make_victim(tmp_path / "victim")
    textures = runs_per_attack_value(tmp_path, scene, victim, "frame_weights", ("mean", "unit"))
    assert not np.array_equal(textures["mean"], textures["unit"])
