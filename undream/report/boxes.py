"""A detector's boxes drawn on an enlarged frame of the contact sheet (PIL).

Boxes of the object's class in :data:`OBJECT_RGB`, of other classes in
:data:`OTHER_RGB`, of an unnamed class (results written before rows named
it) in :data:`UNNAMED_RGB`; each with a ``label score`` tag in its colour.
The object's true box (its mask box) is a thin dashed line, black and white
so that it shows on any render. Boxes are in frame pixels; a picture is the
frame enlarged ``factor`` times with its top-left corner at ``origin``
(sheet pixels).
"""
from __future__ import annotations

from typing import Any

from undream.report.data import Box, Detection
from undream.report.draw import font

OBJECT_RGB = (0, 230, 64)  # the object's class
OTHER_RGB = (255, 0, 200)  # any other class
UNNAMED_RGB = (255, 210, 0)  # class not recorded (old results)
TAG_PX, LINE_W, DASH = 11, 2, 4  # tag font size, box line width, truth dash length (sheet px)
TAG_INK = (0, 0, 0)
Rect = tuple[int, int, int, int]  # x0, y0, x1, y1 in sheet pixels, inclusive


def box_colour(det: Detection, object_label: str) -> tuple[int, int, int]:
    """The colour of ``det``: the object's class (names match with ``_`` as a space), another, or unnamed."""
    if det.label is None:
        return UNNAMED_RGB
    same = det.label.replace("_", " ").lower() == object_label.replace("_", " ").lower()
    return OBJECT_RGB if same else OTHER_RGB


def tag_text(det: Detection) -> str:
    """``label score`` (the score with 2 decimals; the score alone when the class is not recorded)."""
    return f"{det.score:.2f}" if det.label is None else f"{det.label} {det.score:.2f}"


def _scaled(box: Box, origin: tuple[int, int], factor: int, limit: Rect) -> Rect:
    """``box`` (frame pixels, x1/y1 exclusive) in sheet pixels, inclusive corners, inside ``limit``."""
    x, y = origin
    lx0, ly0, lx1, ly1 = limit
    x0, y0 = round(x + box[0] * factor), round(y + box[1] * factor)
    x1, y1 = round(x + box[2] * factor) - 1, round(y + box[3] * factor) - 1
    return (int(min(max(x0, lx0), lx1)), int(min(max(y0, ly0), ly1)),
            int(min(max(x1, lx0), lx1)), int(min(max(y1, ly0), ly1)))


def _dashed(draw: Any, rect: Rect) -> None:
    """A 1 px rectangle of alternating white and black dashes."""
    x0, y0, x1, y1 = rect
    edges = [((x, y0) for x in range(x0, x1 + 1)), ((x, y1) for x in range(x0, x1 + 1)),
             ((x0, y) for y in range(y0, y1 + 1)), ((x1, y) for y in range(y0, y1 + 1))]
    for edge in edges:
        for i, point in enumerate(edge):
            draw.point(point, fill=(255, 255, 255) if (i // DASH) % 2 == 0 else (0, 0, 0))


def _overlaps(a: Rect, b: Rect) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def tag_rect(box: Rect, text: str, placed: list[Rect], limit: Rect) -> Rect:
    """Where ``text``'s tag goes: just above the box, else inside its top edge, else lower down inside
    it, the first place that covers no tag already ``placed``; all within ``limit``."""
    w, h = int(font(TAG_PX).getlength(text)) + 4, TAG_PX + 3
    x = max(limit[0], min(box[0], limit[2] + 1 - w))
    tops = [box[1] - h] + list(range(box[1] + LINE_W, max(box[1] + LINE_W, box[3] - h + 1) + 1, h))
    rects = [(x, y, x + w - 1, y + h - 1) for y in tops if limit[1] <= y and y + h - 1 <= limit[3]]
    rects = rects or [(x, limit[1], x + w - 1, limit[1] + h - 1)]
    return next((r for r in rects if not any(_overlaps(r, q) for q in placed)), rects[0])


def draw_boxes(draw: Any, picture: Rect, factor: int, detections: list[Detection],
               truth: Box | None, object_label: str) -> None:
    """The true box (dashed), the detections' outlines lowest score first, then their ``label score``
    tags best first, each where it covers no tag placed before it.

    ``picture``: the enlarged frame's box in the sheet (x0, y0, x1, y1, x1/y1 exclusive).
    """
    origin = picture[0], picture[1]
    limit = picture[0], picture[1], picture[2] - 1, picture[3] - 1
    if truth is not None:
        _dashed(draw, _scaled(truth, origin, factor, limit))
    ranked = sorted(detections, key=lambda d: -d.score)
    rects = [_scaled(d.box, origin, factor, limit) for d in ranked]
    for det, rect in reversed(list(zip(ranked, rects))):
        draw.rectangle(rect, outline=box_colour(det, object_label), width=LINE_W)
    placed: list[Rect] = []
    for det, rect in zip(ranked, rects):
        text = tag_text(det)
        tag = tag_rect(rect, text, placed, limit)
        placed.append(tag)
        draw.rectangle(tag, fill=box_colour(det, object_label))
        draw.text((tag[0] + 2, tag[1] + 1), text, fill=TAG_INK, font=font(TAG_PX))


def legend(object_label: str, unnamed: bool = False) -> list[tuple[str, tuple[int, int, int]]]:
    """The sheet's key to the boxes, as (text, colour) pieces written one after another; ``unnamed``:
    some box has no class name."""
    return [("boxes: ", (34, 34, 34)), (f"■ {object_label}  ", OBJECT_RGB), ("■ other classes  ", OTHER_RGB),
            *([("■ class not recorded  ", UNNAMED_RGB)] if unnamed else []),
            ("┄ true box (object's mask)", (110, 110, 110))]
