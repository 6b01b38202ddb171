"""The engine's choice of gradient: the transport cache where the scene is linear, prb elsewhere, refreshed."""
from __future__ import annotations

import logging
import re
import shutil

import numpy as np
import pytest

from undream.engine.gradient import GradientPath, capture_seed
from undream.errors import RenderError
from undream.render.differentiable import texture_gradient
from undream.render.scene_cache import SceneCache
from undream.scene.layout import frame_xml
from undream.scene.poses import look_at
from undream.scenedir.init import InitOptions, init_scene
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

SPP = 4
IMG = (24, 32)  # (H, W) of the frames


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory, mi):
    frames = tuple(Frame(i, Camera(Transform.from_rows(look_at([0.3 + 0.4 * i, 1.0, 2.2], [0, 0.5, 0])), 35.0,
                                   IMG[::-1]), Transform.identity(), Environment("clear", 13.0))
                   for i in range(2))
    seq = Sequence("gp", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    return init_scene(seq, tmp_path_factory.mktemp("gp") / "scene", InitOptions(verify_spp=1))


@pytest.fixture(scope="module")
def nonlinear_dir(scene_dir, tmp_path_factory):
    """The same scene with indirect light in its gradient scenes: not linear in the texture."""
    d = tmp_path_factory.mktemp("nl") / "scene"
    shutil.copytree(scene_dir, d)
    for i in range(2):
        xml = frame_xml(d, "grad", i)
        xml.write_text(re.sub(r'name="max_depth" value="2"', 'name="max_depth" value="3"', xml.read_text()))
    return d


def _inputs(seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(0.1, 0.9, (8, 16, 3)).astype(np.float32),
            rng.normal(size=(*IMG, 3)).astype(np.float32))


def _cos(a, b):
    return float((a * b).sum() / (np.linalg.norm(a) * np.linalg.norm(b)))


def test_auto_uses_the_transport_and_matches_prb_at_its_seed(scene_dir):
    scenes = SceneCache(scene_dir)
    path = GradientPath(scenes, "auto", refresh=5, run_seed=3)
    tex, g = _inputs()
    got = path.texture_gradient(1, tex, g, SPP, iteration=2, seed=99)
    assert path.method(1) == "transport"
    s = capture_seed(3, 1, 0)
    ref = texture_gradient(scenes, 1, tex, g, SPP, s + 1, s)  # prb with the capture's sample pattern
    assert _cos(got, ref) > 0.99999
    assert np.linalg.norm(got - ref) <= 1e-5 * np.linalg.norm(ref)
    scenes.close()


def test_transport_is_captured_again_each_refresh(scene_dir):
    scenes = SceneCache(scene_dir)
    path = GradientPath(scenes, "auto", refresh=3, run_seed=0)
    tex, g = _inputs(1)
    grads = [path.texture_gradient(0, tex, g, SPP, iteration=k, seed=10 + k) for k in range(4)]
    assert np.array_equal(grads[0], grads[1]) and np.array_equal(grads[1], grads[2])  # one capture, deterministic
    assert not np.array_equal(grads[2], grads[3])  # iteration 3 starts epoch 1: a new sample pattern
    assert _cos(grads[2], grads[3]) > 0.5  # ... of the same gradient
    scenes.close()


def test_prb_mode_is_the_prb_backward(scene_dir):
    scenes = SceneCache(scene_dir)
    path = GradientPath(scenes, "prb")
    tex, g = _inputs(2)
    got = path.texture_gradient(0, tex, g, SPP, iteration=0, seed=40)
    assert path.method(0) == "prb"
    # prb sums samples with parallel atomics: equal to float rounding, not bit for bit
    np.testing.assert_allclose(got, texture_gradient(scenes, 0, tex, g, SPP, 40, 41), rtol=1e-4, atol=1e-7)
    scenes.close()


def test_a_nonlinear_scene_falls_back_to_prb_with_a_reason(nonlinear_dir, caplog):
    scenes = SceneCache(nonlinear_dir)
    tex, g = _inputs(3)
    with caplog.at_level(logging.WARNING, logger="undream.engine.gradient"):
        got = GradientPath(scenes, "auto").texture_gradient(0, tex, g, SPP, iteration=0, seed=7)
    assert "max_depth" in caplog.text
    np.testing.assert_allclose(got, texture_gradient(scenes, 0, tex, g, SPP, 7, 8), rtol=1e-4, atol=1e-7)
    with pytest.raises(RenderError, match="frame 0 cannot use the transport cache.*max_depth"):
        GradientPath(scenes, "transport").texture_gradient(0, tex, g, SPP, iteration=0, seed=7)
    scenes.close()


def test_bad_mode_names_the_choices(scene_dir):
    with pytest.raises(RenderError, match="auto, transport, prb"):
        GradientPath(SceneCache(scene_dir), "sparse")


@pytest.mark.parametrize("mode", ["prb", "transport"])
def test_a_nan_image_gradient_marks_the_frame_non_finite(scene_dir, monkeypatch, mode):
    """The victim's NaN must reach the reduce step: prb's backward would turn it into zeros."""
    from types import SimpleNamespace

    import undream.engine.job as job
    from undream.engine.crops import CropFrames
    from undream.sim import make_backend
    from undream.spec.run import RunConfig

    scenes = SceneCache(scene_dir)
    ctx = SimpleNamespace(config=RunConfig(scene=str(scene_dir), sim_spp=2, grad_spp=2, crop="off"),
                          frame_indices=[0, 1], sim=make_backend("mitsuba", scene_dir, scenes=scenes),
                          gradients=GradientPath(scenes, mode))
    ctx.crops = CropFrames(ctx)  # crop: off renders whole frames through ctx.sim
    bad = np.full((*IMG, 3), np.nan, np.float32)
    monkeypatch.setattr(job, "victim_pass", lambda ctx, positions, images, iteration=None: ([0.5], [bad], [None]))
    res = job.render_and_grad(ctx, 0, np.full((8, 16, 3), 0.5, np.float32), 0)
    assert not res.finite
    if mode == "prb" and scenes.mi.variant().startswith("llvm"):
        assert np.isfinite(res.grad).all()  # what the old check looked at, and let through (on the CPU)
    scenes.close()


def test_a_shared_shelf_saves_the_second_process_its_captures(scene_dir, tmp_path, monkeypatch):
    """Two processes (two gradient paths) of one scene: the second reads the first's capture and verdict."""
    import undream.render.transport as transport
    from scheduler.transports import BlobTransportShelf
    from undream.store.blobs import BlobStore

    shelf_a = BlobTransportShelf(BlobStore(tmp_path / "blobs"), "scenes/abc123.tar")
    shelf_b = BlobTransportShelf(BlobStore(tmp_path / "blobs"), "scenes/abc123.tar")
    tex, g = _inputs(4)
    scenes_a, scenes_b = SceneCache(scene_dir), SceneCache(scene_dir)
    first = GradientPath(scenes_a, "auto", refresh=5, run_seed=2, shelf=shelf_a)
    ga = first.texture_gradient(1, tex, g, SPP, iteration=6, seed=3)
    assert shelf_a.misses == 1
    calls = []
    monkeypatch.setattr(transport, "capture_transport", lambda *a: calls.append(a))
    monkeypatch.setattr(transport, "check_linear", lambda *a: calls.append(a))
    second = GradientPath(scenes_b, "auto", refresh=5, run_seed=2, shelf=shelf_b)
    gb = second.texture_gradient(1, tex, g, SPP, iteration=7, seed=4)  # same epoch: the same capture
    assert calls == [] and shelf_b.hits == 1
    np.testing.assert_array_equal(ga, gb)
    scenes_a.close()
    scenes_b.close()


def test_a_transport_blob_torn_by_a_power_cut_is_captured_again(scene_dir, tmp_path):
    """Transports are written without an fsync: one cut short (what a power cut may leave) is a
    miss for the next process, which captures it again, to the same gradient (to float rounding)."""
    from scheduler.transports import BlobTransportShelf
    from undream.store.blobs import BlobStore

    blobs = BlobStore(tmp_path / "blobs")
    tex, g = _inputs(4)
    scenes_a, scenes_b = SceneCache(scene_dir), SceneCache(scene_dir)
    ga = GradientPath(scenes_a, "auto", refresh=5, run_seed=2, shelf=BlobTransportShelf(blobs, "scenes/x.tar")) \
        .texture_gradient(1, tex, g, SPP, iteration=6, seed=3)
    (key,) = [i.key for i in blobs.listing("transports") if i.key.endswith(".npz")]
    path = blobs.backend.local_path(key)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    shelf_b = BlobTransportShelf(BlobStore(tmp_path / "blobs"), "scenes/x.tar")
    gb = GradientPath(scenes_b, "auto", refresh=5, run_seed=2, shelf=shelf_b) \
        .texture_gradient(1, tex, g, SPP, iteration=7, seed=4)
    assert shelf_b.misses == 1 and shelf_b.hits == 0
    np.testing.assert_allclose(gb, ga, rtol=1e-5, atol=1e-6)  # a capture's film weights are atomic sums
    scenes_a.close()
    scenes_b.close()


def test_transport_save_load_round_trip(scene_dir, tmp_path):
    from undream.render.transport import Transport, capture_transport

    scenes = SceneCache(scene_dir)
    t = capture_transport(scenes, 0, SPP, 21)
    t.save(tmp_path / "t.npz")
    u = Transport.load(tmp_path / "t.npz")
    assert (u.image_shape, u.texture_shape, u.seed_grad, u.spp, u.index) == \
        (t.image_shape, t.texture_shape, t.seed_grad, t.spp, t.index)
    for a, b in zip(t.jt, u.jt):
        assert (a != b).nnz == 0 and a.dtype == b.dtype
    scenes.close()
