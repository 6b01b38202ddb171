"""A run's contact sheet: one row per frame, benign and adversarial side by side, enlarged; the
report writes one such row per frame (``frames/``) and the grid's thumbnails (:func:`frame_files`).

Each row starts with a band in the colour of its split (:data:`ATTACKED_RGB`
for frames the attack optimised on, :data:`HELD_OUT_RGB` for held-out ones,
named in the band) and frames its two pictures in that colour; under each
picture the victim's prediction and confidence (green: still the object's
class or detected; red: not). A detector's boxes (its five best, with class
and score) and the object's true box are drawn on the pictures
(:mod:`undream.report.boxes`, keyed in the header).
:func:`contact_sheet` returns the picture and its :class:`SheetLayout`
(pixel boxes of every row), which the page and the tests read.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from undream.errors import StoreError
from undream.report import boxes
from undream.report.data import FrameData, RunData, Side
from undream.report.draw import INK, PAPER, encode_png, enlarge, font
from undream.report.grid import THUMB_PX
from undream.report.tables import condition_of

ATTACKED_RGB = (31, 111, 178)
HELD_OUT_RGB = (233, 160, 59)
RIGHT_RGB = (26, 127, 55)
WRONG_RGB = (200, 30, 45)
MIN_SIDE = 160  # px: a frame's short side is enlarged by a whole factor to at least this
MAX_WIDTH = 480  # px: ... unless that makes it wider than this
BAND_W, PAD, BORDER, TEXT_H, HEAD_H = 120, 8, 3, 22, 46  # px
KEY_H = 20  # px: a detector's box key, a line under the title

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (x1, y1 exclusive)


@dataclass(frozen=True)
class RowBox:
    """Where one frame's row lies in the sheet (pixels)."""

    index: int
    held_out: bool
    band: Box
    benign: Box  # the enlarged benign picture
    adversarial: Box


@dataclass(frozen=True)
class SheetLayout:
    width: int
    height: int
    factor: int  # enlargement of every frame
    rows: list[RowBox]


def scale_factor(height: int, width: int) -> int:
    """The whole enlargement that brings the short side to :data:`MIN_SIDE` px, width ≤ :data:`MAX_WIDTH`."""
    want = -(-MIN_SIDE // max(1, min(height, width)))
    return max(1, min(want, MAX_WIDTH // max(1, width)))


def prediction_text(side: Side, task: str) -> tuple[str, tuple[int, int, int]]:
    """What the victim said about one picture, and the colour to write it in."""
    row = side.row
    if task == "detection":
        n = int(row.get("n_detections") or 0)
        ok = bool(row.get("detected"))
        return (f"{'detected' if ok else 'missed'} · best {float(row.get('score') or 0.0):.2f} · "
                f"{n} box{'es' if n != 1 else ''}", RIGHT_RGB if ok else WRONG_RGB)
    ok = bool(row.get("correct"))
    score = row.get("score")
    shown = "" if score is None else f"  p={float(score):.2f}"
    return f"{'✓' if ok else '✗'} {row.get('class')}{shown}", RIGHT_RGB if ok else WRONG_RGB


def _layout(frames: list[FrameData], h: int, w: int, factor: int, head: int = HEAD_H) -> SheetLayout:
    cell_w, cell_h = w * factor, h * factor
    row_h = cell_h + 2 * BORDER + TEXT_H + PAD
    x_b = BAND_W + PAD + BORDER
    x_a = x_b + cell_w + 2 * BORDER + PAD
    rows = []
    for i, f in enumerate(frames):
        y = head + i * row_h + BORDER
        rows.append(RowBox(f.index, f.held_out, (0, y - BORDER, BAND_W, y + cell_h + BORDER + TEXT_H),
                           (x_b, y, x_b + cell_w, y + cell_h), (x_a, y, x_a + cell_w, y + cell_h)))
    return SheetLayout(x_a + cell_w + BORDER + PAD, head + len(frames) * row_h, factor, rows)


def _picture(draw: Any, sheet: Any, side: Side, box: Box, factor: int, colour: tuple[int, int, int],
             data: RunData) -> None:
    x0, y0, x1, y1 = box
    sheet.paste(Image.fromarray(np.ascontiguousarray(enlarge(side.image, factor))), (x0, y0))
    draw.rectangle((x0 - BORDER, y0 - BORDER, x1 + BORDER - 1, y1 + BORDER - 1), outline=colour, width=BORDER)
    if data.task == "detection":
        boxes.draw_boxes(draw, box, factor, side.boxes, side.truth, data.label)
    text, ink = prediction_text(side, data.task)
    draw.text((x0, y1 + BORDER + 3), text, fill=ink, font=font(13))


def _band(draw: Any, row: RowBox) -> None:
    colour = HELD_OUT_RGB if row.held_out else ATTACKED_RGB
    draw.rectangle((row.band[0], row.band[1], row.band[2] - 1, row.band[3] - 1), fill=colour)
    draw.text((8, row.band[1] + 6), f"frame {row.index}", fill=PAPER, font=font(14))
    draw.text((8, row.band[1] + 26), "held-out" if row.held_out else "attacked", fill=PAPER, font=font(13))


def _key(data: RunData) -> list[tuple[str, tuple[int, int, int]]]:
    """A detector's box key (:func:`undream.report.boxes.legend`); [] for a classifier."""
    if data.task != "detection":
        return []
    sides = [s for f in data.frames for s in (f.benign, f.adversarial)]
    return boxes.legend(data.label, any(d.label is None for s in sides for d in s.boxes))


def contact_sheet(data: RunData, frames: list[FrameData] | None = None, note: str = "") -> tuple[Any, SheetLayout]:
    """The sheet of ``frames`` (default: every frame of ``data``; a PIL RGB image) and its layout;
    frames must share one size. ``note``: added to the title line."""
    frames = data.frames if frames is None else frames
    sizes = {f.benign.image.shape[:2] for f in frames} | {f.adversarial.image.shape[:2] for f in frames}
    if len(sizes) != 1:
        raise StoreError(f"run {data.run.id}: frames of different sizes {sorted(sizes)}; one sheet needs one")
    (h, w), = sizes
    key = _key(data)
    layout = _layout(frames, h, w, scale_factor(h, w), HEAD_H + (KEY_H if key else 0))
    title = f"{data.run.name} · object '{data.label}' · {note + ' · ' if note else ''}frames ×{layout.factor}"
    key_w = sum(int(font(12).getlength(text)) for text, _ in key)
    sheet = Image.new("RGB", (max(layout.width, int(font(14).getlength(title)) + 16, key_w + 16), layout.height),
                      PAPER)
    draw = ImageDraw.Draw(sheet)
    draw.text((8, 6), title, fill=INK, font=font(14))
    x = 8
    for text, ink in key:
        draw.text((x, 26), text, fill=ink, font=font(12))
        x += int(font(12).getlength(text))
    if layout.rows:
        first = layout.rows[0]
        for title, box in (("benign texture", first.benign), ("adversarial texture", first.adversarial)):
            draw.text((box[0], 26 + (KEY_H if key else 0)), title, fill=INK, font=font(13))
    for frame, row in zip(frames, layout.rows):
        colour = HELD_OUT_RGB if row.held_out else ATTACKED_RGB
        _band(draw, row)
        _picture(draw, sheet, frame.benign, row.benign, layout.factor, colour, data)
        _picture(draw, sheet, frame.adversarial, row.adversarial, layout.factor, colour, data)
    return sheet, layout


def thumbnail(image: np.ndarray) -> Any:
    """A frame (H×W×3 uint8 sRGB) as its grid thumbnail (PIL): as it is up to
    :data:`~undream.report.grid.THUMB_PX` px on its long side (the page enlarges it), shrunk to that
    (box filter) when larger."""
    pic = Image.fromarray(np.ascontiguousarray(image))
    side = max(pic.width, pic.height)
    if side <= THUMB_PX:
        return pic
    return pic.resize((max(1, round(pic.width * THUMB_PX / side)), max(1, round(pic.height * THUMB_PX / side))),
                      Image.Resampling.BOX)


def frame_files(data: RunData) -> dict[str, bytes]:
    """Per frame: ``frames/frame_NNNN.png``, its row of the contact sheet (benign and adversarial
    enlarged, with the victim's verdict and a detector's boxes), and ``thumbs/{benign,adversarial}/
    frame_NNNN.png``, the grid's thumbnails."""
    files, where = {}, condition_of(data.results)
    for frame in data.frames:
        name = f"frame_{frame.index:04d}.png"
        note = "condition {}, view {}".format(*where[frame.index]) if frame.index in where else ""
        files[f"frames/{name}"] = encode_png(contact_sheet(data, [frame], note)[0])
        for view, side in (("benign", frame.benign), ("adversarial", frame.adversarial)):
            files[f"thumbs/{view}/{name}"] = encode_png(thumbnail(side.image))
    return files
