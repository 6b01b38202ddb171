"""Crop rendering: an iteration renders the object's window on a base (undream.engine.crops).

What must hold: the window never cuts the object (a moving object, a camera path, an object
partly off-screen); the composited frame equals the whole render wherever the texture cannot
reach; a run renders windows during its iterations and whole frames in its evaluation; EOT
conditions and ``crop: off`` render whole frames.
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from farm_support import make_victim
from undream.engine.context import build_context
from undream.engine.crops import BASE_ITERATION, BASE_SEED
from undream.engine.job import frame_seed
from undream.render.crop import Window, composite, crop_window
from undream.render.differentiable import render_linear
from undream.scene.poses import look_at
from undream.scenedir.init import InitOptions, init_scene
from undream.scenedir.verify import read_mask
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec.run import RunConfig

RES = (48, 48)


def _moved(x: float, y: float, z: float) -> Transform:
    return Transform.from_rows([[1, 0, 0, x], [0, 1, 0, y], [0, 0, 1, z], [0, 0, 0, 1]])


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory, mi):
    """A small sphere far from the camera: frame 0 still, 1–2 the object moving, 3 the camera
    moving along a path, 4 the object half off the frame's right edge."""
    def cam(eye, at=(0.0, 0.5, 0.0)):
        return Camera(Transform.from_rows(look_at(list(eye), list(at))), 40.0, RES)

    env = Environment("cloudy", 12.0)
    frames = (
        Frame(0, cam([0.0, 1.5, 7.0]), Transform.identity(), env),
        Frame(1, cam([0.0, 1.5, 7.0]), _moved(0.8, 0.0, 0.0), env),
        Frame(2, cam([0.0, 1.5, 7.0]), _moved(-0.9, 0.3, 0.5), env),
        Frame(3, cam([3.0, 2.0, 6.0], at=(0.9, 0.2, 0.0)), Transform.identity(), env),
        Frame(4, cam([0.0, 1.5, 7.0], at=(-2.15, 0.5, 0.0)), Transform.identity(), env),
    )
    seq = Sequence("crop", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    return init_scene(seq, tmp_path_factory.mktemp("crop") / "scene", InitOptions(verify_spp=1))


@pytest.fixture(scope="module")
def victim_dir(tmp_path_factory):
    return make_victim(tmp_path_factory.mktemp("victim") / "tiny")


def _config(scene_dir, victim_dir, **kw):
    return RunConfig(**{"scene": str(scene_dir), "name": "crop", "victim": victim_dir, "loss": "ce",
                        "attack": {"name": "pgd", "eps": 64.0, "steps": 2}, "sim_spp": 4, "grad_spp": 4,
                        "crop_min_pixels": 0, "eval_spp": 4, "seed": 3, "holdout": "none", **kw})


def test_window_is_the_mask_box_grown_and_clipped():
    mask = np.zeros((40, 60), bool)
    mask[10:20, 30:34] = True  # 10 rows × 4 columns
    assert crop_window(mask, 0.25) == Window(27, 7, 37, 23)  # grown by ceil(0.25 × 10) = 3
    assert crop_window(mask, 0.0) == Window(30, 10, 34, 20)
    edge = np.zeros((40, 60), bool)
    edge[0:6, 55:60] = True  # against the top-right corner: clipped, never outside the frame
    assert crop_window(edge, 0.5) == Window(52, 0, 60, 9)
    assert crop_window(np.zeros((40, 60), bool), 0.25) is None
    big = np.zeros((40, 60), bool)
    big[5:35, 10:50] = True
    assert crop_window(big, 0.0) == Window(10, 5, 50, 35)  # half the frame: still a window
    assert crop_window(big, 0.1) is None  # grown by 4 px: more than half the frame, rendered whole


def test_composite_takes_the_window_and_keeps_the_base_elsewhere():
    base = np.zeros((8, 10, 3), np.float32)
    window, rendered_window = Window(3, 2, 6, 5), Window(1, 0, 8, 7)
    rendered = np.arange(7 * 7 * 3, dtype=np.float32).reshape(7, 7, 3)
    out = composite(base, window, rendered, rendered_window)
    assert np.array_equal(out[2:5, 3:6], rendered[2:5, 2:5])
    outside = np.ones((8, 10), bool)
    outside[2:5, 3:6] = False
    assert not out[outside].any() and not base.any()
    with pytest.raises(ValueError, match="crop render has shape"):
        composite(base, window, rendered[:3], rendered_window)


def test_a_window_never_cuts_the_object(scene_dir, victim_dir):
    ctx = build_context(_config(scene_dir, victim_dir), scene_dir)
    windows = {}
    for index in ctx.frame_indices:
        mask = read_mask(scene_dir, index)
        window = ctx.crops.window(index)
        assert mask.any(), f"frame {index}: the object must show for this test"
        assert window is not None, f"frame {index}: a small object gets a window"
        outside = mask.copy()
        outside[window.slices] = False
        assert not outside.any(), f"frame {index}: the window {window} cuts the object"
        windows[index] = window
    assert windows[1] != windows[0] != windows[2]  # the window follows the moving object
    assert windows[3] != windows[0]  # and the camera's path
    assert windows[4].x1 == RES[0] and read_mask(scene_dir, 4)[:, -1].any()  # cut by the frame, not the window


def test_composite_equals_the_whole_render_where_the_texture_cannot_reach(scene_dir, victim_dir, tmp_path):
    """With direct light only, the texture reaches the object's own pixels and no others: outside
    the window the composited frame must equal the whole frame rendered with the same texture and
    the base's seed, to float rounding."""
    direct = tmp_path / "scene"
    shutil.copytree(scene_dir, direct)
    for xml in (direct / "frames").glob("sim_*.xml"):
        text = xml.read_text()
        assert '<integer name="max_depth" value="6"/>' in text
        xml.write_text(text.replace('<integer name="max_depth" value="6"/>', '<integer name="max_depth" value="2"/>'))
    ctx = build_context(_config(direct, victim_dir), direct)
    texture = np.random.default_rng(0).random((8, 16, 3)).astype(np.float32)
    for index in (0, 4):
        window = ctx.crops.window(index)
        frame = ctx.crops.render(index, texture, 4, 1234)
        whole = render_linear(ctx.scenes, index, texture, 4, frame_seed(BASE_SEED, BASE_ITERATION, index))
        outside = np.ones(frame.shape[:2], bool)
        outside[window.slices] = False
        assert np.abs(frame - whole)[outside].max() <= 1e-5
        assert np.abs(frame - ctx.crops.base(index, 4))[window.slices].max() > 1e-3  # the texture changed it


def _count_windows(monkeypatch):
    import undream.render.differentiable as diff

    calls = []
    original = diff.render_window

    def counted(*args, **kwargs):
        calls.append(args[-1])
        return original(*args, **kwargs)

    monkeypatch.setattr(diff, "render_window", counted)
    return calls


def test_a_run_renders_windows_in_its_iterations_and_whole_frames_in_its_evaluation(
        scene_dir, victim_dir, tmp_path, monkeypatch):
    from PIL import Image

    from scheduler.local import run_local

    calls = _count_windows(monkeypatch)
    res = run_local(_config(scene_dir, victim_dir), tmp_path / "crop", progress=False)
    assert len(calls) == 2 * 5  # every frame of both iterations
    assert len(res["loss_per_iteration"]) == 2 and all(np.isfinite(res["loss_per_iteration"]))
    for png in (tmp_path / "crop" / "frames_adversarial").glob("*.png"):
        assert Image.open(png).size == RES
    again = run_local(_config(scene_dir, victim_dir), tmp_path / "again", progress=False)
    assert np.array_equal(np.load(tmp_path / "crop" / "texture_final.npy"),
                          np.load(tmp_path / "again" / "texture_final.npy"))
    # the film sums samples with parallel atomics: losses agree to float32 rounding, not bit for bit
    # (docs/runs.md, "Reproducibility"); exact equality failed about one run in three
    assert np.allclose(again["loss_per_iteration"], res["loss_per_iteration"], rtol=1e-6, atol=0)


@pytest.mark.parametrize("extra", [{"crop": "off"}, {"eot": {"camera_turn_deg": 2.0}}, {"crop_min_pixels": 10**6}],
                         ids=["off", "eot", "frames-below-crop_min_pixels"])
def test_crop_off_and_eot_render_whole_frames(scene_dir, victim_dir, tmp_path, monkeypatch, extra):
    from scheduler.local import run_local

    calls = _count_windows(monkeypatch)
    run_local(_config(scene_dir, victim_dir, **extra), tmp_path / "whole", progress=False)
    assert calls == []


def test_bad_crop_settings_are_refused_naming_the_field(scene_dir):
    from undream.errors import SpecError

    with pytest.raises(SpecError, match="crop"):
        RunConfig(scene=str(scene_dir), crop="on")
    with pytest.raises(SpecError, match="crop_margin"):
        RunConfig(scene=str(scene_dir), crop_margin=-1)
    with pytest.raises(SpecError, match="crop_min_pixels"):
        RunConfig(scene=str(scene_dir), crop_min_pixels=-1)
    assert RunConfig(scene=str(scene_dir)).crop_min_pixels == 128 * 128  # 64-px frames are rendered whole
