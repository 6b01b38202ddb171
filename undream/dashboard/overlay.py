"""A detector's boxes over a run page's frame: an inline SVG the size of the picture, drawn by the browser.

A frame goes out at its own size and the page enlarges it (pixelated) to
:data:`SIDE` CSS px; boxes drawn into the picture would be enlarged with a
64-px frame and shrunk with a 512-px one, so they are vector shapes laid
over it in the page's pixels instead: lines 2 px and ``label score`` tags
11 px whatever the frame's size, crisp at any zoom. Colours, tags and where
a tag goes are the report's contact sheet's (:mod:`undream.report.boxes`):
the object's class green, other classes magenta, a class not recorded
yellow, the true box a thin black-and-white dashed line. Only SVG attributes,
no ``style``: the dashboard's Content-Security-Policy allows no inline style.
"""
from __future__ import annotations

from typing import Any

from markupsafe import Markup, escape

from undream.report.boxes import DASH, LINE_W, TAG_INK, TAG_PX, Rect, box_colour, legend, tag_text, tag_rect
from undream.report.data import Detection
from undream.report.draw import font

SIDE = 256  # CSS px: a frame's side on the run page (dashboard.css ``.shot img``)


def _hex(rgb: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def _rect(box: list[float], size: tuple[int, int]) -> Rect:
    """``box`` (frame pixels, x1/y1 exclusive) in page pixels, inclusive corners, inside the picture."""
    sx, sy = SIDE / size[0], SIDE / size[1]
    x0, y0, x1, y1 = round(box[0] * sx), round(box[1] * sy), round(box[2] * sx) - 1, round(box[3] * sy) - 1
    return tuple(int(min(max(v, 0), SIDE - 1)) for v in (x0, y0, x1, y1))  # type: ignore[return-value]


def _detections(pred: dict[str, Any]) -> list[Detection]:
    """The prediction's ``detections`` (``{box, score, label}``), best first."""
    dets = [Detection(tuple(float(v) for v in d["box"]), float(d["score"]), d.get("label"))  # type: ignore[arg-type]
            for d in pred.get("detections") or []]
    return sorted(dets, key=lambda d: -d.score)


def _outline(rect: Rect, colour: str) -> str:
    """A :data:`LINE_W` px outline inside ``rect`` (as PIL draws the sheet's)."""
    x0, y0, x1, y1 = rect
    half = LINE_W / 2
    return (f'<rect x="{x0 + half}" y="{y0 + half}" width="{max(x1 - x0 + 1 - LINE_W, 0)}" '
            f'height="{max(y1 - y0 + 1 - LINE_W, 0)}" fill="none" stroke="{colour}" stroke-width="{LINE_W}"/>')


def _truth(rect: Rect) -> str:
    """A 1 px rectangle of alternating white and black dashes of :data:`DASH` px."""
    x0, y0, x1, y1 = rect
    box = f'x="{x0 + 0.5}" y="{y0 + 0.5}" width="{x1 - x0}" height="{y1 - y0}" fill="none" stroke-width="1"'
    return (f'<g class="truth"><title>true box (the object\'s mask)</title><rect {box} stroke="#ffffff"/>'
            f'<rect {box} stroke="#000000" stroke-dasharray="{DASH} {DASH}"/></g>')


def boxes_svg(pred: dict[str, Any] | None) -> Markup:
    """The ``<svg class="boxes">`` laid over a frame of :data:`SIDE` px: the true box (dashed), the
    detections' outlines lowest score first, then their ``label score`` tags best first, each where
    it covers no tag placed before it. Empty for a classifier's prediction, or one without the
    frame's ``size``."""
    size = (pred or {}).get("size")
    if not pred or "detections" not in pred or not size:
        return Markup("")
    size = (int(size[0]), int(size[1]))
    object_label = str(pred.get("truth_label") or "")
    parts = [_truth(_rect(pred["truth_box"], size))] if pred.get("truth_box") else []
    ranked = _detections(pred)
    rects = [_rect(list(d.box), size) for d in ranked]
    parts += [_outline(r, _hex(box_colour(d, object_label))) for d, r in reversed(list(zip(ranked, rects)))]
    placed: list[Rect] = []
    limit = (0, 0, SIDE - 1, SIDE - 1)
    for det, rect in zip(ranked, rects):
        text = tag_text(det)
        tag = tag_rect(rect, text, placed, limit)
        placed.append(tag)
        width = int(font(TAG_PX).getlength(text))
        parts.append(f'<g class="tag"><rect x="{tag[0]}" y="{tag[1]}" width="{tag[2] - tag[0] + 1}" '
                     f'height="{tag[3] - tag[1] + 1}" fill="{_hex(box_colour(det, object_label))}"/>'
                     f'<text x="{tag[0] + 2}" y="{tag[1] + TAG_PX}" font-size="{TAG_PX}" fill="{_hex(TAG_INK)}" '
                     f'textLength="{width}" lengthAdjust="spacingAndGlyphs">{escape(text)}</text></g>')
    return Markup(f'<svg class="boxes" viewBox="0 0 {SIDE} {SIDE}" width="{SIDE}" height="{SIDE}" '
                  f'aria-hidden="true">{"".join(parts)}</svg>')


def boxes_key(frames: list[dict[str, Any]]) -> Markup:
    """The page's key to the boxes (:func:`undream.report.boxes.legend`), each piece in its colour as
    an SVG swatch; empty when no frame of ``frames`` (:func:`undream.dashboard.query.eval_frames`
    rows) has boxes."""
    preds = [row[view] for row in frames for view in ("benign", "adversarial")
             if row.get(view) and "detections" in row[view]]
    if not preds:
        return Markup("")
    label = next((str(p["truth_label"]) for p in preds if p.get("truth_label")), "the object")
    unnamed = any(d.get("label") is None for p in preds for d in p["detections"])
    pieces = []
    for text, rgb in legend(label, unnamed)[1:]:
        mark, words = text.split(" ", 1)
        swatch = (f'<rect x="0" y="0" width="10" height="10" fill="{_hex(rgb)}"/>' if mark == "■" else
                  '<rect x="0.5" y="0.5" width="9" height="9" fill="none" stroke="#000000" stroke-dasharray="2 2"/>')
        pieces.append(f'<span class="box-key"><svg width="10" height="10" viewBox="0 0 10 10">{swatch}</svg> '
                      f'{escape(words.strip())}</span>')
    return Markup(f'<p class="muted" id="boxes-key">boxes: {" ".join(pieces)}</p>')
