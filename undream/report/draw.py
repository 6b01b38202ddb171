"""Drawing primitives shared by the report's pictures: fonts, text strips and captions (PIL).

Pictures are RGB uint8 images; sizes in pixels. The font is matplotlib's
bundled DejaVu Sans (a dependency already), so every machine draws the same.
"""
from __future__ import annotations

import functools
import io
import textwrap
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

INK = (34, 34, 34)
MUTED = (110, 110, 110)
PAPER = (255, 255, 255)
CAPTION_PX = 11  # font size of a caption line
CAPTION_CHARS = 110  # a caption line wraps after this many characters


@functools.lru_cache(maxsize=8)
def font(size: int) -> Any:
    """DejaVu Sans at ``size`` px."""
    from matplotlib import font_manager

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)


def enlarge(img: np.ndarray, factor: int) -> np.ndarray:
    """``img`` (H×W×C) repeated ``factor`` times along both axes (nearest neighbour)."""
    return np.repeat(np.repeat(img, factor, axis=0), factor, axis=1)


def decode_png(data: bytes) -> np.ndarray:
    """PNG bytes → H×W×3 uint8 RGB."""
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def encode_png(img: Any) -> bytes:
    """A PIL image or H×W×3 uint8 array → PNG bytes."""
    pic = Image.fromarray(img) if isinstance(img, np.ndarray) else img
    buf = io.BytesIO()
    pic.save(buf, format="PNG")
    return buf.getvalue()


def with_caption(img: Any, caption: str) -> Any:
    """``img`` (a PIL image) with a white strip below it holding ``caption`` (wrapped), small and grey."""
    lines = [part for line in caption.splitlines() for part in textwrap.wrap(line, CAPTION_CHARS) or [""]]
    step = CAPTION_PX + 4
    out = Image.new("RGB", (img.width, img.height + 6 + step * len(lines)), PAPER)
    out.paste(img.convert("RGB"), (0, 0))
    draw = ImageDraw.Draw(out)
    for i, line in enumerate(lines):
        draw.text((6, img.height + 3 + i * step), line, fill=MUTED, font=font(CAPTION_PX))
    return out


def caption_png(png: bytes, caption: str) -> bytes:
    """PNG bytes (a chart) with :func:`with_caption` applied."""
    return encode_png(with_caption(Image.open(io.BytesIO(png)).convert("RGB"), caption))
