"""A frame's texel → pixel light transport, captured once, for cheap texture gradients.

The gradient scene (``prb``, ``max_depth`` 2: direct light only; the object a
``twosided(diffuse(bitmap))``) is linear in the LINEAR texture ``t`` for a
fixed sample pattern: ``I = J·t + b``. Each camera sample that first hits the
object carries ``albedo(uv) ⊙ L_white`` (``L_white``: its radiance with a white
texture; the diffuse BSDF's sampling, next-event estimation and MIS do not
depend on the albedo, and Russian roulette, which would, cannot act before
the second bounce since ``rr_depth`` ≥ 1), the albedo is the bilinear
lookup of ≤ 4 texels, and the film spreads the sample
over nearby pixels with its reconstruction filter, divided by the per-pixel
filter-weight sums (texture-independent). So, per colour channel ``c``::

    J_c = D⁻¹ · F · diag(L_white_c · [first hit is the object]) · B

with ``F`` (pixels × samples) the filter weights, ``D`` their per-pixel sums
over every sample, ``B`` (samples × texels) the bilinear weights. The capture
replays ``prb``'s own primal pass for ``(seed_grad, spp)`` (same sampler
seeding, same rays, same splat positions as ``render_backward``), so ``Jᵀ·g``
equals prb's backward pass at that seed and spp up to float rounding, and
``J·t + b`` equals ``mi.render(scene, spp=spp, seed=seed_grad)``.

The matrices are stored transposed (texels × pixels, CSR, float32) so the
gradient is one sparse mat-vec per channel. A fixed ``seed_grad`` means a
fixed sample pattern: recapture with a new seed from time to time if the
attack should not overfit it (``benchmarks/bench_transport.py`` measures this).
Where a texel's linear albedo is exactly 0, prb's backward pass drops the
BSDF-sampled (sky) part of its derivative (it divides by the albedo); ``Jᵀ·g``
keeps it, which is the true derivative.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from undream.errors import RenderError
from undream.render.differentiable import srgb_decode_grad
from undream.render.scene_cache import ActiveFrame, SceneCache
from undream.scene.layout import frame_xml
from undream.scene.mitsuba_scene import OBJECT_ID

CHECK_SPP = 2  # samples per pixel of check_linear's forward check
CHECK_SEED = 0x7A5  # its seed
CHECK_TOL = 1e-4  # its bound: max |render - (J·t + b)| / max(render)


@dataclass
class Transport:
    """One frame's captured texel → pixel transport of its gradient scene.

    ``jt[c]`` is Jᵀ of colour channel ``c``: a scipy CSR matrix of shape
    (texels Ht·Wt, pixels H·W), float32, rows and columns in C order of the
    (Ht, Wt) texture and (H, W) image. The image is LINEAR radiance, the
    texture LINEAR reflectance.
    """

    jt: tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]
    image_shape: tuple[int, int]  # (H, W) of the render
    texture_shape: tuple[int, int]  # (Ht, Wt) of the texture
    seed_grad: int
    spp: int
    index: int = -1  # the frame it was captured from

    @property
    def nbytes(self) -> int:
        """Bytes held by the three sparse matrices."""
        return int(sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes for m in self.jt))

    @property
    def nnz(self) -> int:
        return int(sum(m.nnz for m in self.jt))

    def vjp(self, grad_linear_image: np.ndarray) -> np.ndarray:
        """d(loss)/d(LINEAR texture) (Ht×Wt×3) from d(loss)/d(LINEAR image) (H×W×3): ``Jᵀ·g``."""
        g = np.asarray(grad_linear_image, dtype=np.float32)
        if g.shape != (*self.image_shape, 3):
            raise RenderError(f"image gradient has shape {g.shape}, the render's is {(*self.image_shape, 3)}")
        g = g.reshape(-1, 3)
        out = np.empty((self.jt[0].shape[0], 3), np.float32)
        for c in range(3):
            out[:, c] = self.jt[c] @ np.ascontiguousarray(g[:, c])
        return out.reshape(*self.texture_shape, 3)

    def save(self, path) -> None:
        """Write the transport as an uncompressed ``.npz`` (what :meth:`load` reads back exactly)."""
        arrays = {"meta": np.array([*self.image_shape, *self.texture_shape, self.seed_grad, self.spp, self.index],
                                   np.int64)}
        for c, m in enumerate(self.jt):
            arrays.update({f"data{c}": m.data, f"indices{c}": m.indices, f"indptr{c}": m.indptr})
        with open(path, "wb") as f:
            np.savez(f, **arrays)

    @classmethod
    def load(cls, path) -> "Transport":
        """A transport written by :meth:`save`."""
        with np.load(path) as z:
            h, w, th, tw, seed_grad, spp, index = (int(v) for v in z["meta"])
            jt = tuple(sp.csr_matrix((z[f"data{c}"], z[f"indices{c}"], z[f"indptr{c}"]), shape=(th * tw, h * w))
                       for c in range(3))
        return cls(jt, (h, w), (th, tw), seed_grad, spp, index)  # type: ignore[arg-type]

    def forward(self, texture_linear: np.ndarray) -> np.ndarray:
        """``J·t`` (H×W×3, linear radiance) for a LINEAR texture (Ht×Wt×3); the render is this plus ``b``.

        ``b`` (what the scene shows with a black texture) is not stored: this is for checks.
        """
        t = np.asarray(texture_linear, dtype=np.float32)
        if t.shape != (*self.texture_shape, 3):
            raise RenderError(f"texture has shape {t.shape}, the transport's is {(*self.texture_shape, 3)}")
        t = t.reshape(-1, 3)
        out = np.empty((self.jt[0].shape[1], 3), np.float32)
        for c in range(3):
            out[:, c] = self.jt[c].T @ np.ascontiguousarray(t[:, c])
        return out.reshape(*self.image_shape, 3)


def texture_gradient_cached(transport: Transport, texture_srgb: np.ndarray,
                            grad_linear_image: np.ndarray) -> np.ndarray:
    """d(loss)/d(sRGB texture) (Ht×Wt×3) at ``texture_srgb`` from d(loss)/d(LINEAR image) (H×W×3).

    The cached counterpart of :func:`undream.render.differentiable.texture_gradient`
    at the transport's ``seed_grad`` and ``spp``.
    """
    return srgb_decode_grad(texture_srgb, transport.vjp(grad_linear_image))


# -- structure -----------------------------------------------------------------


def _object_shape(scene: Any) -> tuple[int, Any]:
    for i, shape in enumerate(scene.shapes()):
        if shape.id() == OBJECT_ID:
            return i, shape
    raise RenderError(f"the gradient scene has no shape with id '{OBJECT_ID}'")


def _structure_problem(scenes: SceneCache, active: ActiveFrame) -> str | None:
    """Why the frame's gradient scene is not linear in the texture by construction, or None."""
    scene = active.scene
    integrator = scene.integrator()
    name = type(integrator).__name__
    if name != "PRBIntegrator":
        return f"the gradient scene's integrator is {name}, not prb"
    depth = int(integrator.max_depth)
    if depth > 2:
        return (f"the gradient scene's integrator has max_depth {depth} > 2: indirect light lets texels "
                "reach the image through other surfaces")
    if getattr(integrator, "hide_emitters", False):
        return "the gradient scene's integrator hides emitters"
    _, shape = _object_shape(scene)
    if shape.emitter() is not None:
        return "the object is an emitter"
    bsdf = str(shape.bsdf())  # e.g. TwoSided[ brdf[0] = SmoothDiffuse[ reflectance = BitmapTexture[...
    head = bsdf.split("[", 1)[0]
    if head == "TwoSided":
        lobes = [line.strip() for line in bsdf.splitlines() if line.strip().startswith("brdf[")]
        if any(not lobe.split("= ", 1)[-1].startswith("SmoothDiffuse[") for lobe in lobes):
            return "the object's BSDF is twosided but not diffuse on both sides"
    elif head == "SmoothDiffuse":
        lobes = [bsdf]
    else:
        return f"the object's BSDF is {head}, not (twosided) diffuse"
    if bsdf.count("reflectance = BitmapTexture[") != len(lobes):
        return "the object's diffuse reflectance is not a bitmap texture (on every side)"
    if not active.texture_key.endswith("reflectance.data"):
        return f"the texture parameter {active.texture_key} is not the diffuse reflectance"
    return _xml_problem(scenes, active.index)


def _xml_problem(scenes: SceneCache, index: int) -> str | None:
    """The bitmap's filter and wrap mode, which the scene's string form does not show."""
    try:
        root = ET.parse(frame_xml(scenes.dir, "grad", index)).getroot()
    except (OSError, ET.ParseError) as err:
        return f"cannot read the gradient scene file ({err})"
    obj = next((s for s in root.iter("shape") if s.get("id") == OBJECT_ID), None)
    tex = None if obj is None else next((t for t in obj.iter("texture") if t.get("type") == "bitmap"), None)
    if tex is None:
        return "no bitmap texture under the object in the gradient scene file"
    opts = {e.get("name"): e.get("value") for e in tex if e.tag == "string"}
    if opts.get("filter_type", "bilinear") != "bilinear":
        return f"the texture's filter_type is {opts['filter_type']}, not bilinear"
    if opts.get("wrap_mode", "repeat") != "repeat":
        return f"the texture's wrap_mode is {opts['wrap_mode']}, not repeat"
    return None


# -- capture -------------------------------------------------------------------


def capture_transport(scenes: SceneCache, index: int, spp: int, seed_grad: int) -> Transport:
    """Capture frame ``index``'s gradient-scene transport at ``(seed_grad, spp)``.

    Replays prb's primal pass with a white texture (one render's cost), then
    builds the sparse matrices. The scene's texture is put back afterwards.
    Raises :class:`RenderError` when the scene is not linear in the texture by
    construction (see :func:`check_linear`; this does not run its numerical check).
    """
    import drjit as dr

    mi = scenes.mi
    active = scenes.frame("grad", index)
    problem = _structure_problem(scenes, active)
    if problem:
        raise RenderError(f"frame {index}: no transport cache: {problem}")
    scene, params, key = active.scene, active.params, active.texture_key
    saved = type(params[key])(params[key])
    th, tw = (int(v) for v in saved.shape[:2])
    try:
        with dr.suspend_grad():
            params[key] = mi.TensorXf(np.ones((th, tw, 3), np.float32))
            params.update()
            arrays = _replay(mi, scene, spp, seed_grad)
    finally:
        params[key] = saved
        params.update()
    film = scene.sensors()[0].film()
    w, h = (int(v) for v in film.crop_size())
    jt = _assemble(arrays, (h, w), (th, tw), _to_uv(params, key))
    return Transport(jt, (h, w), (th, tw), int(seed_grad), int(arrays["spp"]), index)


def _replay(mi: Any, scene: Any, spp: int, seed: int) -> dict[str, np.ndarray]:
    """prb's primal pass at (seed, spp), per sample: splat position, radiance, first hit."""
    import drjit as dr

    integrator = scene.integrator()
    sensor = scene.sensors()[0]
    film = sensor.film()
    sampler, spp_used = integrator.prepare(sensor, seed, spp, integrator.aov_names())
    ray, weight, pos = integrator.sample_rays(scene, sensor, sampler)
    L, _, _, _ = integrator.sample(mode=dr.ADMode.Primal, scene=scene, sampler=sampler.clone(), ray=ray,
                                   depth=mi.UInt32(0), δL=None, δaovs=None, state_in=None,
                                   active=mi.Bool(True))
    value = L * weight
    si = scene.ray_intersect(mi.Ray3f(ray))
    obj_index, _ = _object_shape(scene)
    obj_ptr = dr.reinterpret_array(mi.UInt32, scene.shapes_dr())[obj_index]
    hit = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == obj_ptr)
    # The film's weight channel: every sample's filter weights summed per pixel (texture-independent).
    block = film.create_block()
    block.put(pos, ray.wavelengths, mi.Color3f(0.0), mi.Float(0.0), mi.Float(1.0))
    weights = block.tensor()
    # One kernel for the integrator's samples and the first hits (evaluated apart, each
    # gather below would trace and run the whole primal pass again).
    dr.eval(value, hit, si.uv, pos, weights)
    # Only samples whose first hit is the object carry the texture: keep those.
    keep = dr.compress(hit & dr.any(value != 0))
    rfilter = film.rfilter()
    b = block.border_size()
    common = {"wsum": np.array(weights, np.float64)[b:weights.shape[0] - b, b:weights.shape[1] - b, -1].ravel(),
              "crop_offset": np.array([int(v) for v in film.crop_offset()], np.int64), "spp": np.array(spp_used)}
    if dr.width(keep) == 0:  # the object is hidden in this frame: an empty transport, a zero gradient
        taps = 1 if rfilter.is_box_filter() else 2 * int(np.ceil(rfilter.radius() - 0.5)) + 1
        return {"value": np.zeros((0, 3), np.float32), "uv": np.zeros((0, 2), np.float32),
                "base": np.zeros((0, 2), np.int64), "wx": np.zeros((0, taps), np.float32),
                "wy": np.zeros((0, taps), np.float32), **common}
    value, uv, pos = dr.gather(type(value), value, keep), dr.gather(mi.Point2f, si.uv, keep), \
        dr.gather(mi.Point2f, pos, keep)
    if rfilter.is_box_filter():  # the image block drops it: one pixel, weight 1
        base = dr.floor(pos)
        wx = wy = [dr.full(mi.Float, 1.0, dr.width(pos))]
    else:  # the image block's footprint: pixels floor(pos) - n .. floor(pos) + n
        n = int(np.ceil(rfilter.radius() - 0.5))
        base = dr.floor(pos) - n
        wx = [rfilter.eval(base.x + k + 0.5 - pos.x) for k in range(2 * n + 1)]
        wy = [rfilter.eval(base.y + k + 0.5 - pos.y) for k in range(2 * n + 1)]
    dr.eval(value, uv, base, wx, wy)
    out = {
        "value": np.stack([np.array(value.x, np.float32), np.array(value.y, np.float32),
                           np.array(value.z, np.float32)], axis=1),
        "uv": np.stack([np.array(uv.x, np.float32), np.array(uv.y, np.float32)], axis=1),
        "base": np.stack([np.array(base.x, np.float64), np.array(base.y, np.float64)], axis=1).astype(np.int64),
        "wx": np.stack([np.array(v, np.float32) for v in wx], axis=1),
        "wy": np.stack([np.array(v, np.float32) for v in wy], axis=1),
        **common,
    }
    del sampler, ray, weight, pos, L, value, si, block
    return out


def _to_uv(params: Any, key: str) -> np.ndarray:
    """The bitmap's ``to_uv`` as a 3×3 matrix (identity when not exposed)."""
    k = key[: -len("data")] + "to_uv"
    if k not in params.keys():
        return np.eye(3)
    return np.array(params[k].matrix, dtype=np.float64).reshape(3, 3)


def _assemble(a: dict[str, np.ndarray], image_hw: tuple[int, int], tex_hw: tuple[int, int],
              to_uv: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
    h, w = image_hw
    th, tw = tex_hw
    n_pix = h * w
    value = a["value"]  # the object samples only (first hit on the object, non-zero radiance)
    px0 = a["base"][:, 0] - a["crop_offset"][0]  # footprint's first pixel column, crop-relative
    py0 = a["base"][:, 1] - a["crop_offset"][1]
    wx, wy = a["wx"].astype(np.float64), a["wy"].astype(np.float64)
    k = wx.shape[1]
    wsum = a["wsum"]  # per-pixel filter-weight sums over every sample (the film's weight channel)
    # F: pixels × (object samples), normalised by the weight sums.
    s = len(value)
    rows, cols, vals = [], [], []
    for ky in range(k):
        py = py0 + ky
        for kx in range(k):
            px = px0 + kx
            wv = wx[:, kx] * wy[:, ky]
            ok = (py >= 0) & (py < h) & (px >= 0) & (px < w) & (wv > 0)
            pix = py[ok] * w + px[ok]
            rows.append(pix)
            cols.append(np.nonzero(ok)[0])
            vals.append(wv[ok] / wsum[pix])
    F = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_pix, s))
    # B: (object samples) × texels, bilinear as Mitsuba's bitmap (Dr.Jit texture, wrap repeat).
    uv = a["uv"].astype(np.float64)
    u = to_uv[0, 0] * uv[:, 0] + to_uv[0, 1] * uv[:, 1] + to_uv[0, 2]
    v = to_uv[1, 0] * uv[:, 0] + to_uv[1, 1] * uv[:, 1] + to_uv[1, 2]
    x = (u * tw - 0.5).astype(np.float32)
    y = (v * th - 0.5).astype(np.float32)
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0).astype(np.float64), (y - y0).astype(np.float64)
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    b_rows = np.tile(np.arange(s), 4)
    b_cols, b_w = [], []
    for dy, wyb in ((0, 1 - fy), (1, fy)):
        for dx, wxb in ((0, 1 - fx), (1, fx)):
            b_cols.append(np.mod(y0 + dy, th) * tw + np.mod(x0 + dx, tw))
            b_w.append(wxb * wyb)
    b_cols_a, b_w_a = np.concatenate(b_cols), np.concatenate(b_w)
    jt = []
    for c in range(3):
        B = sp.csr_matrix((b_w_a * np.tile(value[:, c].astype(np.float64), 4), (b_rows, b_cols_a)),
                          shape=(s, th * tw))
        J = (F @ B).tocsr()  # pixels × texels
        J.eliminate_zeros()
        Jt = J.T.tocsr()
        Jt.sort_indices()
        jt.append(sp.csr_matrix((Jt.data.astype(np.float32), Jt.indices.astype(np.int32),
                                 Jt.indptr.astype(np.int32 if Jt.nnz < 2**31 else np.int64)), shape=Jt.shape))
    return tuple(jt)  # type: ignore[return-value]


# -- checks ----------------------------------------------------------------------


def render_grad_scene(scenes: SceneCache, index: int, texture_linear: np.ndarray, spp: int, seed: int) -> np.ndarray:
    """Frame ``index``'s gradient scene rendered with a LINEAR texture (Ht×Wt×3): H×W×3 linear radiance.

    A plain ``mi.render`` (not frozen), for checks; the scene's texture is put back afterwards.
    """
    mi = scenes.mi
    active = scenes.frame("grad", index)
    params, key = active.params, active.texture_key
    saved = type(params[key])(params[key])
    try:
        params[key] = mi.TensorXf(np.asarray(texture_linear, np.float32))
        params.update()
        return np.array(mi.render(active.scene, spp=spp, seed=seed), dtype=np.float32)
    finally:
        params[key] = saved
        params.update()


def forward_error(scenes: SceneCache, transport: Transport, texture_linear: np.ndarray) -> float:
    """max |render − (J·t + b)| / max(render) at the transport's seed and spp, ``b`` the black-texture render."""
    i, spp, seed = transport.index, transport.spp, transport.seed_grad
    img = render_grad_scene(scenes, i, texture_linear, spp, seed)
    b = render_grad_scene(scenes, i, np.zeros_like(texture_linear), spp, seed)
    err = np.abs(img - (transport.forward(texture_linear) + b)).max()
    return float(err / max(float(np.abs(img).max()), 1e-12))


def check_linear(scenes: SceneCache, index: int) -> str | None:
    """None when the transport cache applies to frame ``index``, else the reason it does not.

    Linearity is checked in two steps. Structurally: the gradient scene's
    integrator is prb with ``max_depth`` ≤ 2 (direct light only; deeper paths
    carry texels through other surfaces; at this depth Russian roulette, whose
    survival probability depends on the albedo, never acts), emitters are not hidden, and the
    object's BSDF is a (twosided) diffuse whose reflectance is a bilinear,
    repeating bitmap (the texture parameter). Numerically: a transport
    captured at ``CHECK_SPP`` spp reproduces the render of a random texture,
    ``mi.render`` at the same seed and spp, as ``J·t + b`` (``b`` the render
    with a black texture) within ``CHECK_TOL`` of the image's maximum.
    """
    active = scenes.frame("grad", index)
    problem = _structure_problem(scenes, active)
    if problem:
        return problem
    transport = capture_transport(scenes, index, CHECK_SPP, CHECK_SEED)
    rng = np.random.default_rng(index)
    tex = rng.uniform(0.0, 1.0, (*transport.texture_shape, 3)).astype(np.float32)
    err = forward_error(scenes, transport, tex)
    if not err <= CHECK_TOL:
        return f"the render is not J·t + b: relative error {err:.2e} > {CHECK_TOL:.0e}"
    return None
