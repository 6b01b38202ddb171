"""``media: auto``: an attack window in a medium rendered clear and mapped into its look (undream.render.media).

What must hold: with the base texture the composite is the base; outside the pixels the texture
reaches it is the base, as the exact (volpath) render is where the texture cannot reach; the
gradient path carries the image gradient through the same ``α`` as the forward map; a bad
``media`` value is one line naming the field. Tiny renders (32 px).
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from farm_support import make_victim
from undream.engine.context import build_context
from undream.engine.crops import BASE_ITERATION, BASE_SEED
from undream.engine.job import frame_seed
from undream.render.differentiable import render_linear
from undream.render.media import fit_gain, nearest_within, transmittance
from undream.scene.poses import look_at
from undream.scenedir.init import InitOptions, init_scene
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec.run import RunConfig

RES = (32, 32)
SPP_FIT = 16  # the runs' sim_spp: at 4 spp the fitted gain is a noise draw (±30 % in this fog)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory, mi):
    """A small sphere 7 m away in fog (frame 0) and in snow's haze (frame 1)."""
    cam = Camera(Transform.from_rows(look_at([0.0, 1.5, 7.0], [0.0, 0.5, 0.0])), 40.0, RES)
    frames = (Frame(0, cam, Transform.identity(), Environment("fog", 12.0, fog_density=0.08)),
              Frame(1, cam, Transform.identity(), Environment("snow", 12.0)))
    seq = Sequence("media", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    return init_scene(seq, tmp_path_factory.mktemp("media") / "scene", InitOptions(verify_spp=1))


@pytest.fixture(scope="module")
def victim_dir(tmp_path_factory):
    return make_victim(tmp_path_factory.mktemp("victim") / "tiny")


def _context(scene_dir, victim_dir, **kw):
    cfg = RunConfig(**{"scene": str(scene_dir), "name": "media", "victim": victim_dir, "loss": "ce",
                       "attack": {"name": "pgd", "eps": 64.0, "steps": 2}, "sim_spp": 4, "grad_spp": 4,
                       "crop_min_pixels": 0, "eval_spp": 4, "seed": 3, "holdout": "none", **kw})
    return build_context(cfg, scene_dir)


def _reached(ctx, index: int, model) -> np.ndarray:
    """The rendered window's pixels the texture reaches in the gradient scene: where a black texture
    changes its render (the object and the filter's reach around it)."""
    black = render_linear(ctx.scenes, index, np.zeros((8, 16, 3), np.float32), 4, model.seed, kind="grad",
                          window=model.rendered)
    return (black != model.g_base).any(axis=2)


def test_with_the_base_texture_the_composite_is_the_base(scene_dir, victim_dir):
    ctx = _context(scene_dir, victim_dir)
    texture = ctx.crops._texture()
    for index in (0, 1):
        model = ctx.crops.medium(index, 4)
        assert model is not None, f"frame {index} holds a medium: its window is mapped"
        assert all(0.05 < k < 20 for k in model.gain), model.gain
        diff = np.abs(ctx.crops.render(index, texture, 4, 777) - ctx.crops.base(index, 4)).max()
        assert diff <= 1e-6, diff


def test_the_map_changes_only_what_the_texture_reaches(scene_dir, victim_dir):
    """Outside the pixels the texture reaches, the mapped frame is the base, up to the last float bits
    of the gradient scene's film (its parallel atomics sum in either order: the same render repeats
    only to ~1e-7 there, docs/runs.md "Reproducibility"); the exact volpath render of another texture
    at the base's seed equals the base there too, up to the light the object throws."""
    ctx = _context(scene_dir, victim_dir)
    texture = np.random.default_rng(0).random((8, 16, 3)).astype(np.float32)
    base = ctx.crops.base(0, 4)
    frame = ctx.crops.render(0, texture, 4, 777)
    model = ctx.crops.medium(0, 4)
    far = np.ones(frame.shape[:2], bool)
    reached = _reached(ctx, 0, model)
    assert 0 < reached.mean() < 0.8, reached.mean()  # the sphere and its rim, not the ground around it
    far[model.rendered.slices] = ~reached
    repeat = np.abs(render_linear(ctx.scenes, 0, ctx.crops._texture(), 4, model.seed, kind="grad",
                                  window=model.rendered) - model.g_base).max()
    assert repeat <= 1e-6, repeat  # the summation order's noise, not a change
    assert np.abs(frame - base)[far].max() <= 1e-6 * max(1.0, float(model.alpha.max()))
    exact = render_linear(ctx.scenes, 0, texture, 4, frame_seed(BASE_SEED, BASE_ITERATION, 0))
    outside = np.ones(frame.shape[:2], bool)
    outside[model.rendered.slices] = False
    assert np.abs(exact - frame)[outside].max() < 0.05 * max(float(base.max()), 1e-6)
    inside = ~far
    assert np.abs(frame - base)[inside].max() > 1e-3  # the texture changed the object's pixels


def test_the_map_follows_volpath_on_the_object(scene_dir, victim_dir):
    """The change a texture makes to the window, mapped (fitted at the runs' 16 spp), against the
    medium's exact change (256 spp on one seed, so that its noise cancels): correlated and of the same
    size, in fog and in snow."""
    ctx = _context(scene_dir, victim_dir)
    texture = np.random.default_rng(1).random((8, 16, 3)).astype(np.float32)
    own = ctx.crops._texture()
    for index in (0, 1):
        window = ctx.crops.window(index)
        mapped = (ctx.crops.render(index, texture, SPP_FIT, 777) - ctx.crops.base(index, SPP_FIT))[window.slices]
        exact = (render_linear(ctx.scenes, index, texture, 256, 99)
                 - render_linear(ctx.scenes, index, own, 256, 99))[window.slices]
        corr = np.corrcoef(exact.ravel(), mapped.ravel())[0, 1]
        scale = float((exact * mapped).sum() / (mapped * mapped).sum())
        assert corr > 0.85 and 0.7 < scale < 1.4, (index, corr, scale)


def test_the_gradient_path_uses_the_same_alpha(scene_dir, victim_dir):
    ctx = _context(scene_dir, victim_dir)
    model = ctx.crops.medium(0, 4)
    window = ctx.crops.window(0)
    g = np.random.default_rng(2).normal(size=(*RES[::-1], 3)).astype(np.float32)
    scaled = ctx.crops.scale_gradient(0, 4, g)
    expected = np.zeros_like(g)
    expected[window.slices] = g[window.slices] * model.alpha[window.within(model.rendered)]
    assert np.array_equal(scaled, expected)
    # the forward map's derivative in the gradient scene's image is that α: a finite difference
    texture = ctx.crops._texture()
    bumped = np.clip(texture + 0.2, 0, 1)
    g_new = render_linear(ctx.scenes, 0, bumped, 4, model.seed, kind="grad", window=model.rendered)
    d_frame = ctx.crops.render(0, bumped, 4, 5) - ctx.crops.base(0, 4)
    inner = window.within(model.rendered)
    assert np.allclose(d_frame[window.slices], (model.alpha * (g_new - model.g_base))[inner], atol=1e-6)
    assert np.array_equal(ctx.crops.scale_gradient(0, 4, g, conditions=object()), g)  # EOT: whole frames


def test_exact_and_clear_scenes_keep_volpath_windows(scene_dir, victim_dir, tmp_path):
    ctx = _context(scene_dir, victim_dir, media="exact")
    assert ctx.crops.medium(0, 4) is None
    clear = tmp_path / "clear"
    shutil.copytree(scene_dir, clear)
    seq_file = clear / "sequence.json"
    seq_file.write_text(seq_file.read_text().replace('"fog"', '"cloudy"').replace('"snow"', '"cloudy"'))
    assert _context(clear, victim_dir).crops.medium(0, 4) is None


def test_fit_gain_transmittance_and_the_rim_distance():
    rng = np.random.default_rng(3)
    dg = rng.random((6, 5, 3))
    trans = transmittance(rng.uniform(1, 30, (6, 5)), 0.05)
    dv = dg * trans[..., None] * np.array([0.4, 0.5, 0.6])
    assert np.allclose(fit_gain(dv, dg, trans), (0.4, 0.5, 0.6))
    assert fit_gain(dv, np.zeros_like(dg), trans) == (1.0, 1.0, 1.0)
    assert transmittance(np.array([np.inf]), 0.1)[0] == 0.0
    d = np.full((6, 6), np.inf)
    d[3, 3] = 4.0  # the object in one pixel: its rim within the filter's reach takes its distance
    assert nearest_within(d, 2)[1, 1] == 4.0 and nearest_within(d, 2)[0, 0] == np.inf


def test_bad_media_value_is_one_line_naming_the_field(scene_dir):
    from undream.errors import SpecError

    with pytest.raises(SpecError, match="media") as err:
        RunConfig(scene=str(scene_dir), media="approx")
    assert "\n" not in str(err.value)
