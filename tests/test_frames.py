"""Per-frame rendering with a texture, and the texture gradient against finite differences."""
from __future__ import annotations

import numpy as np
import pytest

from undream.errors import RenderError
from undream.color import linear_to_srgb, srgb_to_linear
from undream.render.scene_cache import SceneCache
from undream.render.differentiable import (
    render_linear, srgb_decode_grad, srgb_encode_grad, texture_gradient,
)
from undream.scenedir.init import InitOptions, init_scene
from undream.scene.poses import look_at
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

TEX_HW = (4, 8)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, mi):
    cam = Camera(Transform.from_rows(look_at([0.3, 1.0, 2.2], [0, 0.5, 0])), 35.0, (16, 16))
    seq = Sequence("fd", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=TEX_HW[::-1])),
                   (Frame(0, cam, Transform.identity(), Environment("clear", 13.0)),))
    d = init_scene(seq, tmp_path_factory.mktemp("fd") / "scene", InitOptions(verify_spp=1))
    return SceneCache(d, mi)


def test_srgb_chain_rules_match_finite_differences():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.01, 0.95, 200).astype(np.float64)
    h = 1e-5
    enc = (linear_to_srgb(x + h).astype(np.float64) - linear_to_srgb(x - h)) / (2 * h)
    assert srgb_encode_grad(x, np.ones_like(x)) == pytest.approx(enc, rel=2e-2)
    dec = (srgb_to_linear(x + h).astype(np.float64) - srgb_to_linear(x - h)) / (2 * h)
    assert srgb_decode_grad(x, np.ones_like(x)) == pytest.approx(dec, rel=2e-2)


def test_texture_gradient_agrees_with_central_differences(scenes):
    rng = np.random.default_rng(1)
    tex = rng.uniform(0.3, 0.7, (*TEX_HW, 3)).astype(np.float32)
    w = rng.uniform(0.5, 1.5, (16, 16, 3)).astype(np.float32)  # loss = sum(w * linear image)
    grad = texture_gradient(scenes, 0, tex, w, spp=256, seed=3, seed_grad=4)

    def loss(t):
        img = render_linear(scenes, 0, t, spp=512, seed=7, kind="grad").astype(np.float64)
        return float((img * w).sum())

    texels = [tuple(i) for i in np.argwhere(np.abs(grad).sum(axis=2) > 0)]
    assert len(texels) >= 4, "the camera should see several texels"
    picked = [texels[i] for i in rng.choice(len(texels), size=min(6, len(texels)), replace=False)]
    h = 0.05
    fd, ad = [], []
    for r, c in picked:
        for ch in range(3):
            plus, minus = tex.copy(), tex.copy()
            plus[r, c, ch] += h
            minus[r, c, ch] -= h
            fd.append((loss(plus) - loss(minus)) / (2 * h))
            ad.append(grad[r, c, ch])
    fd, ad = np.array(fd), np.array(ad)
    cos = fd @ ad / (np.linalg.norm(fd) * np.linalg.norm(ad))
    assert cos >= 0.95, (cos, fd, ad)


def test_render_rejects_bad_textures(scenes):
    with pytest.raises(RenderError, match="shape"):
        render_linear(scenes, 0, np.zeros((2, 2, 3)), spp=1, seed=0)
    bad = np.full((*TEX_HW, 3), 0.5, np.float32)
    bad[0, 0, 0] = np.nan
    with pytest.raises(RenderError, match="NaN"):
        render_linear(scenes, 0, bad, spp=1, seed=0)
    with pytest.raises(RenderError, match="seed_grad"):
        texture_gradient(scenes, 0, np.full((*TEX_HW, 3), 0.5, np.float32), np.ones((16, 16, 3)), 4, 1, 1)
