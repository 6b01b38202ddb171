"""Writes stop_sign_face.png: the built-in stop sign's texture with a real STOP face.

The sign's front face is the main chart of the UV atlas of ``builtin:stop_sign`` and of
``builtin:stop_sign_plate`` (undream/scene/builtin.py), the same: the regular octagon 0.75 m across flats, upright,
at u = 0.876·x + 0.368, v = 1.901 − 0.876·y (x, y in metres; texture row =
v · height). On it: a red octagon (MUTCD red, sRGB 0.70, 0.07, 0.09) inside a
white rim of 2 cm, and the word STOP in white, 0.22 m tall, as on a real sign.
Everything else (the back, the edge band and the pole) is galvanised grey.

    .venv/bin/python examples/textures/make_stop_face.py [--size 256]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

RED, WHITE, GREY = (179, 18, 23), (244, 244, 244), (150, 152, 155)
ACROSS, CENTRE_Y = 0.75, 1.75  # metres: across flats, centre height (builtin.stop_sign)
U_OF_X, U0, V_OF_Y, V0 = 0.876039, 0.367582, -0.876039, 1.900651  # the front chart's affine map


def uv_px(x: float, y: float, size: int) -> tuple[float, float]:
    """Texture pixel (column, row) of the sign-face point (x, y) in metres."""
    return (U_OF_X * x + U0) * size, (V_OF_Y * y + V0) * size


def octagon(radius_flats: float, size: int) -> list[tuple[float, float]]:
    circ = radius_flats / math.cos(math.pi / 8)
    return [uv_px(circ * math.cos(a), CENTRE_Y + circ * math.sin(a), size)
            for a in (math.pi / 8 + k * math.pi / 4 for k in range(8))]


def stop_face(size: int) -> Image.Image:
    img = Image.new("RGB", (size, size), GREY)
    draw = ImageDraw.Draw(img)
    draw.polygon(octagon(ACROSS / 2, size), fill=WHITE)
    draw.polygon(octagon(ACROSS / 2 - 0.02, size), fill=RED)
    px_per_m = U_OF_X * size
    font = ImageFont.load_default(size=max(8, round(0.26 * px_per_m)))
    cx, cy = uv_px(0.0, CENTRE_Y, size)
    draw.text((cx, cy), "STOP", fill=WHITE, font=font, anchor="mm",
              stroke_width=max(1, round(0.012 * px_per_m)), stroke_fill=WHITE)
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="texture width and height in texels")
    args = ap.parse_args()
    out = Path(__file__).with_name("stop_sign_face.png")
    stop_face(args.size).save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
