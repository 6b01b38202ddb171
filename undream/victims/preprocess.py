"""Differentiable image preprocessing for victims: resize, centre crop, normalise.

Input images are sRGB values in [0, 1], ``B×3×H×W`` float tensors (what the
simulator renders and what a texture is made of). Hugging Face image
processors work on 8-bit images with PIL or torchvision and break the
gradient; here the same steps run in torch so that ``d loss / d image``
exists. The steps, in order:

1. resize (bilinear, ``align_corners=False``; antialiasing off unless asked),
2. centre crop,
3. ``(x - mean) / std`` per channel.

:meth:`PreprocessConfig.from_hf` reads the JSON of a Hugging Face
``preprocessor_config.json`` (no processor class is built: those need
torchvision or PIL and are not differentiable).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import torch
import torch.nn.functional as F

from undream.errors import VictimError

RGB = tuple[float, float, float]


def _fail(field: str, value: Any, expected: str) -> VictimError:
    return VictimError(f"preprocess.{field}: {expected}, got {value!r}")


def _pos_int(field: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise _fail(field, value, "must be a positive integer")
    return value


def _pair(field: str, value: Any) -> tuple[int, int]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise _fail(field, value, "must be (height, width)")
    return (_pos_int(f"{field}[0]", value[0]), _pos_int(f"{field}[1]", value[1]))


def _rgb(field: str, value: Any, positive: bool) -> RGB:
    if not isinstance(value, (tuple, list)) or len(value) != 3:
        raise _fail(field, value, "must be 3 numbers (R, G, B)")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise _fail(field, value, "must be 3 finite numbers")
        if positive and v <= 0:
            raise _fail(field, value, "must be 3 numbers > 0")
        out.append(float(v))
    return (out[0], out[1], out[2])


@dataclass(frozen=True)
class PreprocessConfig:
    """How a victim turns sRGB [0, 1] images into its model's input.

    Resize (at most one of):
        size: fixed output ``(height, width)`` in pixels (aspect not kept).
        shortest_edge: scale so the shorter side has this many pixels, keeping
            the aspect; ``longest_edge`` caps the longer side (DETR's rule).
        longest_edge alone: scale so the longer side has this many pixels.
        none of them: no resize.
    crop: centre crop ``(height, width)`` after the resize, or None.
    mean, std: per-channel normalisation of [0, 1] values.
    antialias: antialiased resize (off by default: plain bilinear).
    """

    size: tuple[int, int] | None = None
    shortest_edge: int | None = None
    longest_edge: int | None = None
    crop: tuple[int, int] | None = None
    mean: RGB = (0.0, 0.0, 0.0)
    std: RGB = (1.0, 1.0, 1.0)
    antialias: bool = False

    def __post_init__(self) -> None:
        if self.size is not None:
            object.__setattr__(self, "size", _pair("size", self.size))
            if self.shortest_edge is not None or self.longest_edge is not None:
                raise _fail("size", self.size, "cannot be combined with shortest_edge/longest_edge")
        for name in ("shortest_edge", "longest_edge"):
            if getattr(self, name) is not None:
                _pos_int(name, getattr(self, name))
        if self.crop is not None:
            object.__setattr__(self, "crop", _pair("crop", self.crop))
        object.__setattr__(self, "mean", _rgb("mean", self.mean, positive=False))
        object.__setattr__(self, "std", _rgb("std", self.std, positive=True))
        if not isinstance(self.antialias, bool):
            raise _fail("antialias", self.antialias, "must be true or false")

    @classmethod
    def from_hf(cls, d: Mapping[str, Any], antialias: bool = False) -> "PreprocessConfig":
        """From the dict of a Hugging Face ``preprocessor_config.json``.

        Understands ``size`` as ``{"height", "width"}``, ``{"shortest_edge"[,
        "longest_edge"]}``, ``{"longest_edge"}`` or an int (with the old
        ``max_size`` key: DETR), ConvNeXt's ``crop_pct``, ``do_center_crop``
        with ``crop_size``, and ``image_mean``/``image_std``. ``do_rescale`` is
        implied: inputs are already in [0, 1]. Padding is not needed: a batch
        tensor has one size.
        """
        size: tuple[int, int] | None = None
        short: int | None = None
        long: int | None = None
        crop: tuple[int, int] | None = None
        raw = d.get("size")
        if d.get("do_resize", True) and raw is not None:
            size, short, long = _hf_size(raw, d.get("max_size"), edge=d.get("crop_pct") is not None)
            pct = d.get("crop_pct")
            if pct is not None and short is not None and long is None:
                # ConvNeXt: below 384 px resize to s / crop_pct, then crop s × s.
                if short < 384:
                    crop, short = (short, short), int(short / float(pct))
                else:
                    size, short = (short, short), None
        if d.get("do_center_crop") and d.get("crop_size") is not None:
            crop, _, _ = _hf_size(d["crop_size"], None)
            if crop is None:
                raise _fail("crop_size", d["crop_size"], "must be an int or a dict with height/width")
        mean, std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
        if d.get("do_normalize", True) and d.get("image_mean") is not None:
            mean = tuple(d["image_mean"])  # type: ignore[assignment]
            std = tuple(d.get("image_std", (1.0, 1.0, 1.0)))  # type: ignore[assignment]
        return cls(size=size, shortest_edge=short, longest_edge=long, crop=crop,
                   mean=mean, std=std, antialias=antialias)

    def resized_size(self, height: int, width: int) -> tuple[int, int]:
        """The ``(height, width)`` after the resize step, before the crop."""
        if self.size is not None:
            return self.size
        if self.shortest_edge is not None:
            return _shortest_edge_size(height, width, self.shortest_edge, self.longest_edge)
        if self.longest_edge is not None:
            scale = self.longest_edge / max(height, width)
            return max(1, int(round(height * scale))), max(1, int(round(width * scale)))
        return height, width

    def output_size(self, height: int, width: int) -> tuple[int, int]:
        """The ``(height, width)`` of the model input for an input of this size."""
        return self.crop if self.crop is not None else self.resized_size(height, width)


def _hf_size(raw: Any, max_size: Any, edge: bool = False
             ) -> tuple[tuple[int, int] | None, int | None, int | None]:
    """Decode a Hugging Face ``size`` entry into (size, shortest_edge, longest_edge).

    A bare int is a square unless ``max_size`` (old DETR configs) or ``edge``
    (old ConvNeXt configs, with ``crop_pct``) make it a shortest edge.
    """
    if isinstance(raw, int) and not isinstance(raw, bool):
        if max_size is not None or edge:
            return None, raw, None if max_size is None else int(max_size)
        return (raw, raw), None, None
    if isinstance(raw, Mapping):
        keys = set(raw)
        if keys == {"height", "width"}:
            return (int(raw["height"]), int(raw["width"])), None, None
        if keys in ({"shortest_edge"}, {"shortest_edge", "longest_edge"}):
            long = raw.get("longest_edge")
            return None, int(raw["shortest_edge"]), None if long is None else int(long)
        if keys == {"longest_edge"}:
            return None, None, int(raw["longest_edge"])
    raise _fail("size", raw, "must be an int or a dict with height/width, shortest_edge"
                "[/longest_edge] or longest_edge (Hugging Face preprocessor_config.json)")


def _shortest_edge_size(height: int, width: int, short: int, long: int | None) -> tuple[int, int]:
    """DETR's rule: shorter side to ``short`` unless the longer would pass ``long``."""
    size = float(short)
    lo, hi = float(min(height, width)), float(max(height, width))
    if long is not None and hi / lo * size > long:
        size = long * lo / hi
    if width < height:
        return max(1, int(size * height / width)), max(1, int(round(size)))
    return max(1, int(round(size))), max(1, int(size * width / height))


def preprocess_images(images: torch.Tensor, cfg: PreprocessConfig) -> torch.Tensor:
    """Resize, crop and normalise ``B×3×H×W`` sRGB [0, 1] images; differentiable.

    Returns ``B×3×h×w`` with ``(h, w) = cfg.output_size(H, W)``, in the model's
    normalised units. The input is not checked here (see
    :func:`undream.victims.base.check_images`).
    """
    h, w = images.shape[-2:]
    rh, rw = cfg.resized_size(h, w)
    x = images
    if (rh, rw) != (h, w):
        x = F.interpolate(x, size=(rh, rw), mode="bilinear", align_corners=False,
                          antialias=cfg.antialias)
    if cfg.crop is not None:
        ch, cw = cfg.crop
        if ch > rh or cw > rw:
            raise VictimError(f"preprocess.crop: {cfg.crop} is larger than the resized image "
                              f"{(rh, rw)} (input {(h, w)})")
        top, left = (rh - ch) // 2, (rw - cw) // 2
        x = x[..., top:top + ch, left:left + cw]
    mean = torch.tensor(cfg.mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(cfg.std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std
