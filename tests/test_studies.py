"""The study scripts' own logic: the Pareto front, and that every case they set up is a valid spec or run."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from scheduler.sweep import set_dotted
from undream.scene.trajectory import sequence_from_trajectory
from undream.spec.run import RunConfig

ROOT = Path(__file__).resolve().parents[1]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_pareto_front_keeps_exactly_the_points_nothing_beats():
    pareto = _script("speed_accuracy").pareto
    points = [(1.0, 5.0), (2.0, 3.0), (3.0, 3.0), (2.5, 4.0), (4.0, 1.0), (4.0, 1.0), (0.5, 9.0)]
    # (3, 3) is beaten by (2, 3) (faster, as good); (2.5, 4) by (2, 3); ties are both kept.
    assert pareto(points) == [0, 1, 4, 5, 6]
    rng = np.random.default_rng(0)
    pts = [tuple(p) for p in rng.uniform(size=(40, 2))]
    front = pareto(pts)
    for i, (x, y) in enumerate(pts):
        dominated = any(x2 <= x and y2 <= y and (x2, y2) != (x, y) for x2, y2 in pts)
        assert (i in front) == (not dominated)


def test_speed_settings_are_valid_run_configs(tmp_path):
    sa = _script("speed_accuracy")
    base = yaml.safe_load((ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml").read_text())
    scenes = {s.scene: tmp_path / s.scene for s in [*sa.SETTINGS, sa.REFERENCE]}
    names = set()
    for s in [*sa.SETTINGS, sa.REFERENCE]:
        config = sa._config(base, scenes, s, 1, "x")
        assert config.seed == 1 and config.scene == str(scenes[s.scene])
        for key, value in s.run.items():
            stored = config.to_json()
            node = stored["attack"] if key.startswith("attack.") else stored
            assert node[key.split(".", 1)[-1]] == value, s.name
        names.add(s.name)
    assert len(names) == len(sa.SETTINGS) + 1, "setting names must be unique (they name the runs)"


@pytest.mark.parametrize("case", ["reference", "pitch_down_90", "pitch_up_90", "grazing", "tiny", "night",
                                  "occluded", "saturated", "flat_ce", "flat_dlr"])
def test_stability_cases_are_valid_specs_and_runs(case):
    st = _script("stability_study")
    spec, overrides = st.cases("some/victim/folder")[case]
    seq = sequence_from_trajectory(spec, ROOT / "examples")
    assert len(seq.frames) == 8
    if case == "pitch_down_90":  # the view direction is parallel to the world's up axis
        forward = np.asarray(seq.frames[0].camera.to_world.matrix)[:3, 2]
        assert np.allclose(forward, [0, -1, 0], atol=1e-6)
    if case == "tiny":
        assert np.linalg.norm(np.asarray(seq.frames[0].camera.to_world.translation)) > 25
    base = yaml.safe_load((ROOT / "examples" / "runs" / "bin_orbit_pgd.yaml").read_text())
    d = {**base, "scene": "x"}
    for key, value in overrides.items():
        set_dotted(d, key, value, case)
    config = RunConfig.from_json(d)
    assert config.attack.eps == overrides.get("attack.eps", base["attack"]["eps"])
    assert base["attack"]["eps"] == 255, "the base config itself is left as it was"
