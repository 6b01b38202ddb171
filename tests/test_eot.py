"""Expectation over conditions: per-iteration camera and light jitter, seeded, applied to one render only."""
from __future__ import annotations

import numpy as np
import pytest

from undream.errors import SpecError
from undream.render.jitter import draw_conditions
from undream.spec.run import RunConfig

EOT = {"camera_shift_m": 0.1, "camera_turn_deg": 3.0, "sun_turn_deg": 20.0, "light_scale": 0.3}


def test_conditions_are_reproducible_per_seed_iteration_and_frame():
    a = draw_conditions(EOT, seed=7, iteration=3, index=5)
    b = draw_conditions(EOT, seed=7, iteration=3, index=5)
    for field in ("camera_shift", "camera_turn", "sun_turn"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.light == b.light
    others = [draw_conditions(EOT, 8, 3, 5), draw_conditions(EOT, 7, 4, 5), draw_conditions(EOT, 7, 3, 6)]
    assert all(not np.array_equal(o.camera_shift, a.camera_shift) for o in others)
    assert draw_conditions(None, 7, 3, 5) is None and draw_conditions({}, 7, 3, 5) is None


def test_conditions_stay_within_their_bounds():
    for k in range(200):
        c = draw_conditions(EOT, 0, k, 0)
        assert np.abs(c.camera_shift).max() <= 0.1 and 0.7 <= c.light <= 1.3
        for rot, most in ((c.camera_turn, 3.0), (c.sun_turn, 20.0)):
            np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
            angle = np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1)))
            assert angle <= most + 1e-9
    still = draw_conditions({"camera_shift_m": 0.0}, 0, 0, 0)
    assert not still.camera_shift.any() and still.light == 1.0
    np.testing.assert_allclose(still.camera_turn, np.eye(3), atol=1e-15)


@pytest.mark.parametrize("changes, needle", [
    ({"eot": {"camera_shift_m": -1}}, "eot.camera_shift_m: must be in [0, 10] (metres)"),
    ({"eot": {"fov": 2}}, "eot.fov: unknown field"),
    ({"eot": {"light_scale": 0.2}, "gradient": "transport"}, "gradient: cannot be 'transport' with eot"),
    ({"eot": {"light_scale": 0.2}, "sim": "blender"}, "eot: needs sim: mitsuba"),
])
def test_bad_eot_blocks_name_the_field(changes, needle):
    with pytest.raises(SpecError) as err:
        RunConfig(scene="x", **changes)
    assert needle in str(err.value)


def _render(scenes, index, conditions=None, kind="sim"):
    from undream.render.differentiable import render_linear

    tex = np.full((128, 128, 3), 0.5, np.float32)
    return render_linear(scenes, index, tex, spp=4, seed=11, kind=kind, conditions=conditions)


@pytest.mark.parametrize("frozen", [True, False])
def test_a_jittered_render_moves_the_view_once_and_the_next_render_is_the_frames_own(
        example_scenes, mi, frozen):
    from undream.render.scene_cache import SceneCache

    scenes = SceneCache(example_scenes["bin_park"], mi, frozen=frozen)
    try:
        plain = _render(scenes, 0)
        moved = _render(scenes, 0, draw_conditions(EOT, 0, 1, 0))
        again = _render(scenes, 0)
        assert np.abs(moved - plain).mean() > 0.01 * plain.mean()
        # the frame's own camera and light are back (to the parallel film sums' last bits)
        np.testing.assert_allclose(again, plain, rtol=1e-5, atol=1e-6)
        other = _render(scenes, 1)  # switching frames after a jitter shows that frame as it is
        fresh = SceneCache(example_scenes["bin_park"], mi, frozen=frozen)
        try:
            np.testing.assert_allclose(other, _render(fresh, 1), rtol=1e-5, atol=1e-6)
        finally:
            fresh.close()
    finally:
        scenes.close()


def test_light_scale_alone_scales_the_direct_light_of_the_gradient_scene(example_scenes, mi):
    """The gradient scene is direct light only: scaling sun and sky by s scales its image by s."""
    from undream.render.jitter import Conditions
    from undream.render.scene_cache import SceneCache

    scenes = SceneCache(example_scenes["bin_park"], mi, frozen=False)
    try:
        plain = _render(scenes, 0, kind="grad")
        brighter = _render(scenes, 0, Conditions(np.zeros(3), np.eye(3), np.eye(3), 1.25), kind="grad")
        np.testing.assert_allclose(brighter, 1.25 * plain, rtol=1e-4, atol=1e-6)
    finally:
        scenes.close()


def test_a_run_with_eot_completes(tmp_path):
    """End to end with jitter: every attack iteration's gradient comes from prb at the moved view."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from farm_support import make_scene, make_victim, run_config, write_yaml

    root = Path(__file__).resolve().parents[1]
    scene, victim = make_scene(tmp_path / "scene", n_frames=4, size=16), make_victim(tmp_path / "victim")
    cfg = write_yaml(tmp_path / "run.yaml", run_config(scene, victim, name="eot", steps=3, eot=EOT))
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(cfg), "--out", str(tmp_path / "out"),
                          "--no-progress"], capture_output=True, text=True, cwd=root)
    assert res.returncode == 0, res.stderr
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert len(results["loss_per_iteration"]) == 3 and all(v is not None for v in results["loss_per_iteration"])
    meta = json.loads((tmp_path / "out" / "metadata.json").read_text())
    assert meta["config"]["eot"] == EOT


def test_a_simulator_that_cannot_move_the_camera_refuses_conditions(tmp_path):
    """Run configs refuse eot with sim: blender; the backend itself refuses too, before starting Cycles."""
    from conftest import service_missing
    from undream.errors import RenderError
    from undream.sim.blender import BlenderSimulator

    try:
        sim = BlenderSimulator(tmp_path)
    except RenderError as err:
        service_missing(f"Blender's Python is not installed: {err}")
    with pytest.raises(RenderError, match="sim: blender cannot move the camera and light"):
        sim.render(0, np.zeros((4, 4, 3), np.float32), 1, 0, conditions=draw_conditions(EOT, 0, 0, 0))
    assert sim._proc is None  # nothing was started
