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
``J·t + b`` equals ``mi.render(scene, spp=spp, seed=seed_grad)``. prb runs
only on the lanes whose first hit is the object (each lane draws from its own
random stream, so theirs are the full render's), as one Dr.Jit frozen function
per scene group (with ``SceneCache.frozen``: traced once, then replayed with
the frame's parameters and the seed as inputs). The three channels share
``F`` and ``B``'s pattern and are multiplied in one sparse product.

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
from undream.render.differentiable import render_frozen, srgb_decode_grad
from undream.render.scene_cache import ActiveFrame, SceneCache, update_params
from undream.scene.layout import frame_xml
from undream.scene.mitsuba_scene import OBJECT_ID

CHECK_SPP = 2  # samples per pixel of check_linear's forward check
CHECK_SEED = 0x7A5  # its seed
CHECK_TOL = 1e-4  # its bound: max |render - (J·t + b)| / max(render), on the CPU
# On CUDA Mitsuba filters the bitmap with the GPU's texture units, whose bilinear weights have 8
# fractional bits: a lookup is off by up to 2⁻⁸ of its texels' range (9.2e-4 of the image's maximum
# measured on an H100), against the exact weights J holds. Their gradient is J's all the same.
CHECK_TOL_CUDA = 1e-2


def check_tolerance(variant: str) -> float:
    """:func:`check_linear`'s bound on the relative forward error under Mitsuba variant ``variant``."""
    return CHECK_TOL_CUDA if variant.startswith("cuda") else CHECK_TOL


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
        """Write the transport as an uncompressed ``.npz`` (what :meth:`load` reads back exactly) to
        the file ``path`` or into a binary file object."""
        arrays = {"meta": np.array([*self.image_shape, *self.texture_shape, self.seed_grad, self.spp, self.index],
                                   np.int64)}
        for c, m in enumerate(self.jt):
            arrays.update({f"data{c}": m.data, f"indices{c}": m.indices, f"indptr{c}": m.indptr})
        if hasattr(path, "write"):
            np.savez(path, **arrays)
            return
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
                            grad_linear_image: np.ndarray, deriv: np.ndarray | None = None) -> np.ndarray:
    """d(loss)/d(sRGB texture) (Ht×Wt×3) at ``texture_srgb`` from d(loss)/d(LINEAR image) (H×W×3).

    The cached counterpart of :func:`undream.render.differentiable.texture_gradient`
    at the transport's ``seed_grad`` and ``spp``; ``deriv``: the texture's
    :func:`~undream.render.differentiable.srgb_decode_deriv`, when the caller holds it.
    """
    return srgb_decode_grad(texture_srgb, transport.vjp(grad_linear_image), deriv)


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

    Replays prb's primal pass with a white texture (at most one render's cost:
    prb runs on the samples that hit the object), then builds the sparse
    matrices. The scene's texture is put back afterwards.
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
            update_params(params)
            arrays = _replay(scenes, scene, spp, seed_grad)
    finally:
        params[key] = saved
        update_params(params)
    film = scene.sensors()[0].film()
    w, h = (int(v) for v in film.crop_size())
    jt = _assemble(arrays, (h, w), (th, tw), _to_uv(params, key))
    return Transport(jt, (h, w), (th, tw), int(seed_grad), int(arrays["spp"]), index)


def _replay(scenes: SceneCache, scene: Any, spp: int, seed: int) -> dict[str, np.ndarray]:
    """prb's primal pass at (seed, spp), per object sample: splat position, radiance, uv, filter taps.

    One Dr.Jit evaluation over every camera sample (:func:`_trace`, a frozen function
    with ``scenes.frozen``: traced once per scene group, then replayed with the frame's
    parameters and the seed as inputs), then the samples kept are picked out in numpy.
    """
    import drjit as dr

    mi = scenes.mi
    sensor = scene.sensors()[0]
    film = sensor.film()
    rfilter = film.rfilter()
    taps = 1 if rfilter.is_box_filter() else 2 * int(np.ceil(rfilter.radius() - 0.5)) + 1
    obj_index, _ = _object_shape(scene)
    obj_ptr = mi.UInt32(dr.reinterpret_array(mi.UInt32, scene.shapes_dr())[obj_index])
    args = (scene, mi.UInt32(seed), spp, obj_ptr, taps)
    value, keep, uv, base, wx, wy, weights = (scenes.frozen_call("transport/replay", _trace, *args, scene=scene)
                                              if scenes.frozen else _trace(*args))
    idx = np.flatnonzero(np.array(keep, dtype=bool))
    wsum = np.array(weights, np.float64)
    b = (wsum.shape[0] - int(film.crop_size()[1])) // 2  # the block's border (0 unless the film samples it)
    out = {
        "value": np.stack([np.array(value.x, np.float32)[idx], np.array(value.y, np.float32)[idx],
                           np.array(value.z, np.float32)[idx]], axis=1),
        "uv": np.stack([np.array(uv.x, np.float32)[idx], np.array(uv.y, np.float32)[idx]], axis=1),
        "base": np.stack([np.array(base.x, np.float32)[idx], np.array(base.y, np.float32)[idx]],
                         axis=1).astype(np.int64),
        "wx": np.stack([np.array(v, np.float32)[idx] for v in wx], axis=1),
        "wy": np.stack([np.array(v, np.float32)[idx] for v in wy], axis=1),
        "wsum": wsum[b:wsum.shape[0] - b, b:wsum.shape[1] - b, -1].ravel(),
        "crop_offset": np.array([int(v) for v in film.crop_offset()], np.int64),
        "spp": np.array(_sample_count(sensor, spp)),
    }
    del value, keep, uv, base, wx, wy, weights
    return out


def _trace(scene: Any, seed: Any, spp: int, obj_ptr: Any, taps: int) -> tuple:
    """The Dr.Jit part of :func:`_replay`, per camera sample: radiance × sensor weight, whether the
    sample is kept (first hit the object, non-zero radiance), its uv, its footprint's first pixel and
    filter weights; and the film's weight channel (every sample's filter weights summed per pixel:
    texture-independent)."""
    import drjit as dr
    import mitsuba as mi

    integrator = scene.integrator()
    sensor = scene.sensors()[0]
    film = sensor.film()
    sampler, _ = integrator.prepare(sensor, seed, spp, integrator.aov_names())
    ray, weight, pos = integrator.sample_rays(scene, sensor, sampler)
    si = scene.ray_intersect(mi.Ray3f(ray))
    hit = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == obj_ptr)
    # Only the samples that hit the object carry the texture: prb runs on those lanes alone
    # (each lane draws from its own random stream, so theirs are the full render's).
    L, _, _, _ = integrator.sample(mode=dr.ADMode.Primal, scene=scene, sampler=sampler.clone(), ray=ray,
                                   depth=mi.UInt32(0), δL=None, δaovs=None, state_in=None, active=hit)
    value = L * weight
    block = film.create_block()
    block.put(pos, ray.wavelengths, mi.Color3f(0.0), mi.Float(0.0), mi.Float(1.0))
    rfilter = film.rfilter()
    if rfilter.is_box_filter():  # the image block drops it: one pixel, weight 1
        base = dr.floor(pos)
        wx = wy = [dr.full(mi.Float, 1.0, dr.width(pos))]
    else:  # the image block's footprint: pixels floor(pos) - n .. floor(pos) + n
        base = dr.floor(pos) - (taps - 1) // 2
        wx = [rfilter.eval(base.x + k + 0.5 - pos.x) for k in range(taps)]
        wy = [rfilter.eval(base.y + k + 0.5 - pos.y) for k in range(taps)]
    out = (value, hit & dr.any(value != 0), si.uv, base, wx, wy, block.tensor())
    dr.eval(out)
    return out


def _sample_count(sensor: Any, spp: int) -> int:
    """The samples per pixel prb's ``prepare`` uses for ``spp`` (0: the scene's own)."""
    sampler = sensor.sampler().clone()
    if spp != 0:
        sampler.set_sample_count(spp)
    return int(sampler.sample_count())


def _to_uv(params: Any, key: str) -> np.ndarray:
    """The bitmap's ``to_uv`` as a 3×3 matrix (identity when not exposed)."""
    k = key[: -len("data")] + "to_uv"
    if k not in params.keys():
        return np.eye(3)
    return np.array(params[k].matrix, dtype=np.float64).reshape(3, 3)


def _assemble(a: dict[str, np.ndarray], image_hw: tuple[int, int], tex_hw: tuple[int, int],
              to_uv: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
    """``Jᵀ_c = Bᵀ · diag(value_c) · Fᵀ`` of the three channels in one sparse product.

    The channels share ``F`` and ``B``'s pattern: their ``Bᵀ · diag(value_c)`` are stacked
    (rows ``c·texels + texel``), multiplied once (float64), then split into the channels'
    float32 CSR matrices (texels × pixels; a row's columns in the product's order, not sorted).
    """
    h, w = image_hw
    n_tex = tex_hw[0] * tex_hw[1]
    s = len(a["value"])  # the object samples only (first hit on the object, non-zero radiance)
    texels, bilinear = _bilinear(a["uv"], tex_hw, to_uv)  # (s, 4) each
    value = a["value"].astype(np.float64)
    data = (bilinear[:, None, :] * value[:, :, None]).reshape(-1)  # (s, channel, corner)
    rows = (texels[:, None, :] + n_tex * np.arange(3)[:, None]).reshape(-1)
    bt = sp.csc_matrix((data, rows, np.arange(0, 12 * s + 1, 12)), shape=(3 * n_tex, s)).tocsr()
    jt = bt @ _filter_t(a, image_hw)  # (3 texels) × pixels
    jt.eliminate_zeros()  # the columns of a row stay in the product's order: a matvec needs no sorting
    data, indices = jt.data.astype(np.float32), jt.indices.astype(np.int32)  # pixels < 2**31
    out = []
    for c in range(3):  # each channel's rows, views of the float32 / int32 arrays
        lo, hi = int(jt.indptr[c * n_tex]), int(jt.indptr[(c + 1) * n_tex])
        ptr = (jt.indptr[c * n_tex:(c + 1) * n_tex + 1] - lo).astype(np.int32 if hi - lo < 2**31 else np.int64)
        out.append(sp.csr_matrix((data[lo:hi], indices[lo:hi], ptr), shape=(n_tex, h * w), copy=False))
    return tuple(out)  # type: ignore[return-value]


def _filter_t(a: dict[str, np.ndarray], image_hw: tuple[int, int]) -> sp.csr_matrix:
    """``Fᵀ`` (object samples × pixels, CSR, float64): each sample's filter weights on the pixels of its
    footprint inside the crop, divided by those pixels' weight sums over every sample (the film's)."""
    h, w = image_hw
    s, k = a["wx"].shape
    px0 = a["base"][:, 0] - a["crop_offset"][0]  # footprint's first pixel column, crop-relative
    py0 = a["base"][:, 1] - a["crop_offset"][1]
    taps = np.arange(k)
    in_x = (0 <= px0[:, None] + taps) & (px0[:, None] + taps < w)  # (s, k)
    in_y = (0 <= py0[:, None] + taps) & (py0[:, None] + taps < h)
    # (s, ky, kx) flattened to (s, k²): the footprint's taps row by row; float32 products are exact in float64
    wv = (a["wy"].astype(np.float64)[:, :, None] * a["wx"].astype(np.float64)[:, None, :]).reshape(s, k * k)
    ok = (in_y[:, :, None] & in_x[:, None, :]).reshape(s, k * k) & (wv > 0)
    pix = ((py0 * w + px0)[:, None] + (taps[:, None] * w + taps).ravel())[ok]
    indptr = np.zeros(s + 1, np.int64)
    np.cumsum(ok.sum(axis=1), out=indptr[1:])
    return sp.csr_matrix((wv[ok] / a["wsum"][pix], pix, indptr), shape=(s, h * w))


def _bilinear(uv: np.ndarray, tex_hw: tuple[int, int], to_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's 4 texels (C-order indices) and bilinear weights (float64), both (samples, 4),
    as Mitsuba's bitmap looks them up (Dr.Jit texture, bilinear, wrap repeat) at ``to_uv · uv``."""
    th, tw = tex_hw
    uv = uv.astype(np.float64)
    u = to_uv[0, 0] * uv[:, 0] + to_uv[0, 1] * uv[:, 1] + to_uv[0, 2]
    v = to_uv[1, 0] * uv[:, 0] + to_uv[1, 1] * uv[:, 1] + to_uv[1, 2]
    x = (u * tw - 0.5).astype(np.float32)
    y = (v * th - 0.5).astype(np.float32)
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0).astype(np.float64), (y - y0).astype(np.float64)
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    texels = np.stack([np.mod(y0 + dy, th) * tw + np.mod(x0 + dx, tw) for dy in (0, 1) for dx in (0, 1)], axis=1)
    weights = np.stack([wxb * wyb for wyb in (1 - fy, fy) for wxb in (1 - fx, fx)], axis=1)
    return texels, weights


# -- checks ----------------------------------------------------------------------


def render_grad_scene(scenes: SceneCache, index: int, texture_linear: np.ndarray, spp: int, seed: int) -> np.ndarray:
    """Frame ``index``'s gradient scene rendered with a LINEAR texture (Ht×Wt×3): H×W×3 linear radiance.

    A forward render (frozen when the cache is: the checks of every frame replay one recording),
    for checks; the scene's texture is put back afterwards.
    """
    mi = scenes.mi
    active = scenes.frame("grad", index)
    params, key = active.params, active.texture_key
    saved = type(params[key])(params[key])
    try:
        params[key] = mi.TensorXf(np.asarray(texture_linear, np.float32))
        update_params(params)
        return render_frozen(scenes, "grad", active, spp, seed)
    finally:
        params[key] = saved
        update_params(params)


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
    with a black texture) within :func:`check_tolerance` of the image's maximum.
    """
    active = scenes.frame("grad", index)
    problem = _structure_problem(scenes, active)
    if problem:
        return problem
    transport = capture_transport(scenes, index, CHECK_SPP, CHECK_SEED)
    rng = np.random.default_rng(index)
    tex = rng.uniform(0.0, 1.0, (*transport.texture_shape, 3)).astype(np.float32)
    err = forward_error(scenes, transport, tex)
    tol = check_tolerance(scenes.mi.variant())
    if not err <= tol:
        return f"the render is not J·t + b: relative error {err:.2e} > {tol:.0e}"
    return None
