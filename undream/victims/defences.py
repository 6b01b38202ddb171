"""Input-transform defences: the transforms, their seeded draws and how a gradient passes them.

Every transform takes and returns ``B×3×H×W`` float tensors of sRGB values in [0, 1] (a victim's
input frames) and keeps them in [0, 1]. The settings are :class:`undream.spec.defence.DefenceStep`;
the wrapper that puts a chain of them in front of any victim is :mod:`undream.victims.defended`.

- :func:`jpeg`: real JPEG (Pillow's encoder and decoder, each image quantised to 8 bits first); no
  autograd. :func:`jpeg_approx` is a differentiable approximation of it (the ``smooth`` stand-in).
- :func:`median_smooth`: K×K median filter (edges replicated); autograd passes the gradient to the
  chosen pixel only.
- :func:`gaussian_smooth`: separable Gaussian filter of σ pixels, radius ⌈3σ⌉ (edges replicated);
  exactly differentiable.
- :func:`bit_depth`: rounding to ``2**bits`` levels; autograd passes zero.
- :func:`resize_pad`: bilinear resize to a drawn size placed on a grey canvas at a drawn offset
  (:class:`ResizePadDraw`, drawn by :func:`draw_resize_pad`); exactly differentiable; moves pixels
  (a box maps as ``x * sx + tx``).

:func:`straight_through` is BPDA (Athalye et al. 2018): the forward value of a transform, the
backward pass of a stand-in (the identity, or a smooth function). :func:`backward_rule` says which
backward pass a step gets under a config's ``backward``; :func:`apply_step` applies one step so.
"""
from __future__ import annotations

import hashlib
import io
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from undream.errors import VictimError
from undream.spec.defence import DefenceStep

DEFENCE_STREAM = 0xDEF  # keeps the defences' random numbers apart from every other stream of (seed, iteration, frame)
CONTENT_ITERATION = 2**40  # the "iteration" of a draw keyed by the image's content (no attack iteration is one)
Key = tuple[int, ...]  # one image's draw key: (seed, iteration, frame[, draw])


def _check(images: torch.Tensor, name: str) -> None:
    if not isinstance(images, torch.Tensor) or images.ndim != 4 or images.shape[1] != 3 \
            or not images.is_floating_point():
        raise VictimError(f"{name}: images must be a float tensor B×3×H×W, got "
                          f"{tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__}")


def jpeg(images: torch.Tensor, quality: int) -> torch.Tensor:
    """Each image quantised to 8 bits, JPEG-encoded at ``quality`` (1–100) and decoded (Pillow, its
    default 4:2:0 chroma subsampling): a new tensor of the input's dtype and device, without gradient."""
    _check(images, "jpeg")
    with torch.no_grad():
        u8 = (images.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
    out = []
    for im in u8:
        buf = io.BytesIO()
        Image.fromarray(im).save(buf, format="JPEG", quality=int(quality))
        buf.seek(0)
        with Image.open(buf) as decoded:
            out.append(np.asarray(decoded.convert("RGB")))
    stacked = torch.from_numpy(np.stack(out)).permute(0, 3, 1, 2)
    return (stacked.to(images.dtype) / 255.0).to(images.device)


def median_smooth(images: torch.Tensor, kernel: int) -> torch.Tensor:
    """K×K median of each channel (``kernel`` odd), edges replicated; same shape."""
    _check(images, "median")
    r = int(kernel) // 2
    padded = F.pad(images, (r, r, r, r), mode="replicate")
    patches = padded.unfold(2, int(kernel), 1).unfold(3, int(kernel), 1)  # B×3×H×W×K×K
    return patches.reshape(*patches.shape[:4], -1).median(dim=-1).values


def mean_smooth(images: torch.Tensor, kernel: int) -> torch.Tensor:
    """K×K mean of each channel, edges replicated; same shape (the median's smooth stand-in)."""
    _check(images, "mean")
    r = int(kernel) // 2
    padded = F.pad(images, (r, r, r, r), mode="replicate")
    return F.avg_pool2d(padded, int(kernel), stride=1)


# The JPEG standard's example quantisation tables (ITU-T T.81, Annex K), luminance and chrominance.
_LUMA_Q = (16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56,
           14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
           49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99)
_CHROMA_Q = (17, 18, 24, 47, 99, 99, 99, 99, 18, 21, 26, 66, 99, 99, 99, 99, 24, 26, 56, 99, 99, 99, 99, 99,
             47, 66, 99, 99, 99, 99, 99, 99, *([99] * 32))
_TO_YCC = ((0.299, 0.587, 0.114), (-0.168736, -0.331264, 0.5), (0.5, -0.418688, -0.081312))  # JFIF
_FROM_YCC = ((1.0, 0.0, 1.402), (1.0, -0.344136, -0.714136), (1.0, 1.772, 0.0))


def jpeg_tables(quality: int) -> torch.Tensor:
    """The 3×8×8 quantisation steps (Y, Cb, Cr) of ``quality`` as libjpeg scales the standard's tables."""
    scale = 5000 / quality if quality < 50 else 200 - 2 * quality
    tables = torch.tensor([_LUMA_Q, _CHROMA_Q, _CHROMA_Q], dtype=torch.float64).view(3, 8, 8)
    return ((tables * scale + 50) // 100).clamp(1, 255)


def _dct_matrix() -> torch.Tensor:
    k, n = torch.arange(8, dtype=torch.float64)[:, None], torch.arange(8, dtype=torch.float64)[None]
    c = torch.cos((2 * n + 1) * k * math.pi / 16) * math.sqrt(2 / 8)
    c[0] = math.sqrt(1 / 8)
    return c


def jpeg_approx(images: torch.Tensor, quality: int) -> torch.Tensor:
    """A differentiable approximation of :func:`jpeg` (Shin & Song 2017): JFIF YCbCr, 8×8 block DCT,
    quantisation by ``quality``'s tables with the rounding replaced by ``r + (x − r)³`` (r the nearest
    integer), and back; no chroma subsampling, edges replicated to whole blocks. Its gradient is the
    smooth stand-in of the ``smooth`` backward pass; its value only approximates the codec's."""
    _check(images, "jpeg")
    b, _, h, w = images.shape
    dt = images.dtype
    to_ycc, from_ycc = torch.tensor(_TO_YCC, dtype=dt), torch.tensor(_FROM_YCC, dtype=dt)
    x = torch.einsum("ij,bjhw->bihw", to_ycc.to(images.device), images * 255)
    x = F.pad(x, (0, -w % 8, 0, -h % 8), mode="replicate")
    hp, wp = x.shape[2], x.shape[3]
    blocks = x.unfold(2, 8, 8).unfold(3, 8, 8)  # B×3×(H/8)×(W/8)×8×8
    c = _dct_matrix().to(dt).to(images.device)
    q = jpeg_tables(int(quality)).to(dt).to(images.device).view(1, 3, 1, 1, 8, 8)
    coeffs = (c @ blocks @ c.T) / q
    r = torch.round(coeffs).detach()
    blocks = c.T @ ((r + (coeffs - r) ** 3) * q) @ c
    x = blocks.permute(0, 1, 2, 4, 3, 5).reshape(b, 3, hp, wp)[:, :, :h, :w]
    return (torch.einsum("ij,bjhw->bihw", from_ycc.to(images.device), x) / 255).clamp(0, 1)


def gaussian_kernel(sigma: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The normalised 1-D Gaussian of ``sigma`` pixels over ``2⌈3σ⌉ + 1`` taps."""
    radius = max(1, math.ceil(3 * float(sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / float(sigma)) ** 2)
    return (w / w.sum()).to(dtype)


def gaussian_smooth(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian smoothing of ``sigma`` pixels, edges replicated; same shape."""
    _check(images, "gaussian")
    w = gaussian_kernel(sigma, images.dtype).to(images.device)
    r = (len(w) - 1) // 2
    x = F.pad(images, (r, r, r, r), mode="replicate")
    x = F.conv2d(x, w.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    return F.conv2d(x, w.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)


def bit_depth(images: torch.Tensor, bits: int) -> torch.Tensor:
    """Each value rounded to the nearest of ``2**bits`` levels in [0, 1]; same shape."""
    _check(images, "bits")
    levels = 2 ** int(bits) - 1
    return torch.round(images.clamp(0, 1) * levels) / levels


@dataclass(frozen=True)
class ResizePadDraw:
    """One resize-and-pad: the image resized to ``height×width`` pixels and placed with its top-left
    corner at ``(top, left)`` on a ``canvas`` (height, width) filled with ``fill``."""

    height: int
    width: int
    top: int
    left: int
    canvas: tuple[int, int]
    fill: float

    def affine(self, h: int, w: int) -> tuple[float, float, float, float]:
        """``(sx, sy, tx, ty)``: a point (x, y) in pixels of the ``h×w`` input lands at
        ``(x * sx + tx, y * sy + ty)`` on the canvas."""
        return self.width / w, self.height / h, float(self.left), float(self.top)


def canvas_size(step: DefenceStep, h: int, w: int) -> tuple[int, int]:
    """The canvas of ``step`` (resize_pad) for ``h×w`` images: ``round((1 + pad) × size)``."""
    return max(h, round(h * (1 + step.pad))), max(w, round(w * (1 + step.pad)))


def draw_resize_pad(step: DefenceStep, key: Key, h: int, w: int) -> ResizePadDraw:
    """The resize-and-pad of one ``h×w`` image drawn from ``key`` alone: the scale uniform in
    ``step.scale``, the offset uniform over the places the resized image fits on the canvas."""
    rng = np.random.default_rng([*map(int, key), DEFENCE_STREAM])
    ch, cw = canvas_size(step, h, w)
    s = float(rng.uniform(step.scale[0], step.scale[1]))
    height, width = min(ch, max(1, round(h * s))), min(cw, max(1, round(w * s)))
    top, left = int(rng.integers(0, ch - height + 1)), int(rng.integers(0, cw - width + 1))
    return ResizePadDraw(height, width, top, left, (ch, cw), step.fill)


def resize_pad(images: torch.Tensor, draws: Sequence[ResizePadDraw]) -> torch.Tensor:
    """Each image resized (bilinear) and placed on its canvas as its draw says; the canvases must agree."""
    _check(images, "resize_pad")
    if len(draws) != images.shape[0] or len({d.canvas for d in draws}) > 1:
        raise VictimError(f"resize_pad: needs one draw per image on one canvas size, got {len(draws)} draws "
                          f"for {images.shape[0]} images")
    out = []
    for im, d in zip(images, draws):
        small = F.interpolate(im[None], size=(d.height, d.width), mode="bilinear", align_corners=False)
        ch, cw = d.canvas
        out.append(F.pad(small, (d.left, cw - d.width - d.left, d.top, ch - d.height - d.top), value=d.fill))
    return torch.cat(out)


def content_key(seed: int, image: torch.Tensor) -> Key:
    """A draw key from ``seed`` and the image's 8-bit content: the same frame draws the same
    transform whatever batch it comes in (a call that names no frames: the evaluation, ``predict``)."""
    u8 = (image.detach().clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy().tobytes()
    digest = int.from_bytes(hashlib.sha256(u8).digest()[:6], "little")
    return int(seed), CONTENT_ITERATION, digest


def straight_through(x: torch.Tensor, y: torch.Tensor,
                     stand_in: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """BPDA: the value ``y`` (a transform of ``x``, however computed), the gradient of ``stand_in``
    at ``x`` (the identity when None)."""
    g = x if stand_in is None else stand_in(x)
    return g + (y.detach() - g.detach())


def backward_rule(step: DefenceStep, backward: str) -> str:
    """How an attack differentiates through ``step`` under ``backward`` (auto, bpda, smooth, exact):
    ``exact`` (autograd), ``identity`` (BPDA with the identity), ``mean`` (BPDA with a K×K mean) or
    ``jpeg_approx`` (BPDA with :func:`jpeg_approx`)."""
    if step.kind == "resize_pad" or backward == "exact":
        return "exact"
    if step.kind == "gaussian":
        return "identity" if backward == "bpda" else "exact"
    if step.kind == "median" and backward == "smooth":
        return "mean"
    if step.kind == "jpeg" and backward == "smooth":
        return "jpeg_approx"
    return "identity"


def forward(step: DefenceStep, images: torch.Tensor, draws: Sequence[ResizePadDraw] | None = None) -> torch.Tensor:
    """``step``'s transform of ``images`` (``draws``: resize_pad's, one per image)."""
    if step.kind == "jpeg":
        return jpeg(images, int(step.value))
    if step.kind == "median":
        return median_smooth(images, int(step.value))
    if step.kind == "gaussian":
        return gaussian_smooth(images, step.value)
    if step.kind == "bits":
        return bit_depth(images, int(step.value))
    if draws is None:
        raise VictimError("resize_pad: needs its draws (draw_resize_pad), one per image")
    return resize_pad(images, draws)


def apply_step(step: DefenceStep, images: torch.Tensor, backward: str,
               draws: Sequence[ResizePadDraw] | None = None) -> torch.Tensor:
    """``step``'s transform of ``images``, differentiated as :func:`backward_rule` says."""
    rule = backward_rule(step, backward)
    if rule == "exact" or not images.requires_grad:
        if step.kind == "jpeg" and images.requires_grad:
            raise VictimError("jpeg: has no exact gradient (Pillow's codec); use backward auto, bpda or smooth")
        return forward(step, images, draws)
    with torch.no_grad():
        y = forward(step, images, draws)
    stand_ins = {"mean": lambda x: mean_smooth(x, int(step.value)),
                 "jpeg_approx": lambda x: jpeg_approx(x, int(step.value))}
    return straight_through(images, y, stand_ins.get(rule))
