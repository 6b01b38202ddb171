"""The gradient scene: the texture is differentiable where the camera sees it, and only there."""
from __future__ import annotations

import numpy as np
import pytest

from projection import barycentric
from undream.scenedir.init import InitOptions, init_scene
from undream.scene.mesh import read_ply
from undream.scene.poses import look_at
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

CAM = np.array([0.0, 1.4, 2.6])
CENTRE = np.array([0.0, 0.5, 0.0])
RADIUS = 0.5
TEX_HW = (16, 32)


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory, mi):
    cam = Camera(Transform.from_rows(look_at(CAM, CENTRE)), 40.0, (32, 32))
    seq = Sequence("grad", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=TEX_HW[::-1])),
                   (Frame(0, cam, Transform.identity(), Environment("cloudy", 12.0)),))
    return init_scene(seq, tmp_path_factory.mktemp("grad") / "scene", InitOptions(verify_spp=1))


def _texel_points(mesh, h: int, w: int) -> np.ndarray:
    """World point (H,W,3) under each texel centre (NaN where no triangle maps there)."""
    out = np.full((h, w, 3), np.nan)
    uv = mesh.uvs.astype(float)
    cs, rs = np.meshgrid(np.arange(w), np.arange(h))
    px, py = (cs + 0.5) / w, (rs + 0.5) / h
    for f in mesh.faces:
        bary = barycentric(uv[f], px, py)
        if bary is None:
            continue
        l0, l1, l2 = bary
        inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
        p = l0[..., None] * mesh.vertices[f[0]] + l1[..., None] * mesh.vertices[f[1]] + l2[..., None] * mesh.vertices[f[2]]
        out[rs[inside], cs[inside]] = p[inside]
    return out


def test_texture_gradient_is_nonzero_where_seen_and_zero_where_not(sphere_scene, mi):
    import drjit as dr

    from undream.render.loading import texture_param_key

    scene = mi.load_file(str(sphere_scene / "frames" / "grad_0000.xml"), spp=64)
    params = mi.traverse(scene)
    key = texture_param_key(params)
    params[key] = mi.TensorXf(np.full((*TEX_HW, 3), 0.5, np.float32))
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, seed=0, seed_grad=1)
    dr.backward(img)
    grad = np.abs(np.array(dr.grad(params[key]))).sum(axis=2)

    pts = _texel_points(read_ply(sphere_scene / "meshes" / "object.ply"), *TEX_HW)
    d = np.linalg.norm(CAM - CENTRE)
    cos = ((pts - CENTRE) @ (CAM - CENTRE)) / (RADIUS * d)  # visible iff cos > r / d
    horizon = RADIUS / d
    seen = cos > horizon + 0.15
    unseen = cos < horizon - 0.05
    # bilinear lookups reach one texel around: only texels whose neighbours are unseen too
    shifted = [np.roll(unseen, s, axis=a) for a in (0, 1) for s in (-1, 1)]
    deep_unseen = unseen & np.logical_and.reduce(shifted)
    assert seen.sum() > 40 and deep_unseen.sum() > 100
    assert np.isfinite(grad).all()
    assert (grad[seen] > 0).mean() >= 0.95
    assert np.all(grad[deep_unseen] == 0.0)
