"""A texture as files to print: PNG and PDF at a physical size and DPI, the colour profile embedded.

- **Size**: the texture's real size on its mesh (:func:`undream.printing.size.texel_size`: one
  repeat of it), or a chosen width (``width_cm``; the height keeps the texture's aspect); the
  pixels are that size × ``dpi``, resampled from the texels (``bilinear``, as the renderer samples
  the texture, or ``nearest``: every texel a block of one colour) and, with a printer's gamut,
  projected into it again (bilinear mixes of printable colours may not be printable).
- **PNG**: 8-bit sRGB, littleCMS's sRGB profile embedded (iCCP), the DPI in its pHYs chunk.
- **PDF**: one page of exactly the print's size (points, 1/72 inch), the image lossless (Flate,
  via img2pdf): with a CMYK printer profile, the image is the profile's CMYK separation
  (relative colorimetric, as the gamut was made) with that profile embedded (ICCBased, N 4);
  without one, the sRGB pixels with the sRGB profile (ICCBased, N 3).
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import img2pdf
import numpy as np
from PIL import Image

from undream.color import to_uint8
from undream.errors import PrintError
from undream.printing.gamut import Gamut, to_cmyk
from undream.printing.profiles import srgb_profile
from undream.printing.size import TexelSize

RESAMPLE = {"bilinear": Image.BILINEAR, "nearest": Image.NEAREST}
MAX_DPI = 4800
MAX_PIXELS = 100_000_000  # a 1 m square at 250 DPI; past this, a lower DPI or a smaller print
INCH_M = 0.0254


@dataclass(frozen=True)
class PrintSize:
    """The print: ``width_m`` × ``height_m`` on paper, ``pixels`` (width, height) at ``dpi``."""

    width_m: float
    height_m: float
    dpi: float
    pixels: tuple[int, int]

    @property
    def points(self) -> tuple[float, float]:
        """The page size in PDF points (1/72 inch)."""
        return self.width_m / INCH_M * 72.0, self.height_m / INCH_M * 72.0


def print_size(size: TexelSize, texture_wh: tuple[int, int], dpi: float, width_cm: float | None = None) -> PrintSize:
    """The :class:`PrintSize` of a W×H texture at its real size (``size``) or ``width_cm`` wide, at
    ``dpi``; PrintError (one line) for a DPI outside (0, 4800], a width that is not > 0, or a print
    of more than 100 million pixels."""
    if isinstance(dpi, bool) or not isinstance(dpi, (int, float)) or not math.isfinite(dpi) or not 0 < dpi <= MAX_DPI:
        raise PrintError(f"--dpi: must be a number of dots per inch in (0, {MAX_DPI}], got {dpi!r}")
    w, h = texture_wh
    if width_cm is not None:
        if isinstance(width_cm, bool) or not isinstance(width_cm, (int, float)) or not math.isfinite(width_cm) \
                or width_cm <= 0:
            raise PrintError(f"--width-cm: must be a width in centimetres > 0, got {width_cm!r}")
        width_m = width_cm / 100.0
        height_m = width_m * h / w
    else:
        width_m, height_m = size.width_m, size.height_m
    pixels = (max(1, round(width_m / INCH_M * dpi)), max(1, round(height_m / INCH_M * dpi)))
    if pixels[0] * pixels[1] > MAX_PIXELS:
        raise PrintError(f"--dpi: {width_m * 100:.1f} × {height_m * 100:.1f} cm at {dpi:g} DPI is "
                         f"{pixels[0]} × {pixels[1]} pixels, more than {MAX_PIXELS:,}; give a lower --dpi "
                         "or a smaller --width-cm")
    return PrintSize(width_m, height_m, float(dpi), pixels)


def print_pixels(texture: np.ndarray, size: PrintSize, resample: str = "bilinear",
                 gamut: Gamut | None = None) -> np.ndarray:
    """``texture`` (sRGB H×W×3 in [0, 1]) resampled to ``size.pixels`` as 8-bit sRGB (h×w×3 uint8),
    projected into ``gamut`` when given."""
    if resample not in RESAMPLE:
        raise PrintError(f"--resample: must be one of {', '.join(RESAMPLE)}, got {resample!r}")
    rgb8 = to_uint8(texture)
    if rgb8.shape[1::-1] != size.pixels:
        rgb8 = np.asarray(Image.fromarray(rgb8, "RGB").resize(size.pixels, RESAMPLE[resample]))
    if gamut is not None:
        rgb8 = to_uint8(gamut.project(rgb8.astype(np.float32) / 255.0))
    return rgb8


def write_png(path: Path, rgb8: np.ndarray, dpi: float) -> Path:
    """8-bit sRGB ``rgb8`` as a PNG with the sRGB profile and ``dpi`` (pHYs) in it."""
    Image.fromarray(rgb8, "RGB").save(path, format="PNG", dpi=(dpi, dpi), icc_profile=srgb_profile())
    return path


def write_pdf(path: Path, rgb8: np.ndarray, size: PrintSize, profile: Path | None = None) -> Path:
    """One page of ``size.points`` holding ``rgb8``: as the CMYK separation of ``profile`` with that
    profile embedded, or (``profile`` None) as sRGB with the sRGB profile embedded."""
    if profile is not None:
        image = Image.fromarray(to_cmyk(rgb8, profile), "CMYK")
        icc = profile.read_bytes()
    else:
        image, icc = Image.fromarray(rgb8, "RGB"), srgb_profile()
    buffer = io.BytesIO()
    image.save(buffer, format="TIFF", icc_profile=icc, dpi=(size.dpi, size.dpi), compression="tiff_adobe_deflate")
    try:
        pdf = img2pdf.convert(buffer.getvalue(), layout_fun=img2pdf.get_layout_fun(size.points))
    except (img2pdf.ImageOpenError, ValueError) as err:
        raise PrintError(f"{path.name}: img2pdf cannot write the page ({' '.join(str(err).split())})") from None
    path.write_bytes(pdf)
    return path


def describe(size: PrintSize, texel: TexelSize | None, profile: Path | None, gamut_name: str | None) -> dict[str, Any]:
    """What an export records in ``export.json``."""
    return {"width_cm": round(size.width_m * 100, 4), "height_cm": round(size.height_m * 100, 4),
            "dpi": size.dpi, "pixels": list(size.pixels),
            "real_size_cm": None if texel is None else [round(texel.width_m * 100, 4), round(texel.height_m * 100, 4)],
            "texel_mm": None if texel is None else round(texel.metres * 1000, 4),
            "profile": None if profile is None else str(profile), "profile_name": gamut_name}
