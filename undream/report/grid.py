"""A run's frames as a grid: conditions down, views across (plain data here, and the report's HTML).

A multi-condition run has one row per condition (results.json ``conditions``,
in the run's order), its frames in view order; a run of one scene has one
row of every frame. Each cell is a frame *position* (0 … n−1, the order of
``results.json``'s ``per_frame`` rows). The dashboard's run page lays out
the same rows (:func:`grid_rows`, :func:`page_of`); the report draws them as
thumbnails of the adversarial frames (:func:`grid_html`), each a link to the
frame's full-size picture, with the benign row of a condition one click away
(a ``:target`` link, no script).
"""
from __future__ import annotations

from dataclasses import dataclass
from html import escape
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from undream.report.tables import condition_rows, headline_rows

if TYPE_CHECKING:
    from undream.report.data import FrameData, Side

THUMB_PX = 64  # a thumbnail's long side is shown at about this many CSS pixels
CELLS_W = 1150  # CSS px a row's thumbnails may span (the report's page is 1320 px wide, names beside)
CELL_EXTRA = 9  # CSS px a cell adds to its thumbnail's width (border, gap)


@dataclass(frozen=True)
class GridRow:
    """One row of the grid: a condition (or every frame of a one-scene run) and its frame positions."""

    name: str
    held_out: bool  # the whole condition was held out (never attacked)
    positions: list[int]  # frame positions, in view order
    numbers: dict[str, Any]  # benign, adversarial, metric, success_rate, n_success, n_eligible, n_frames


def grid_rows(results: Mapping[str, Any], indices: Sequence[int]) -> list[GridRow]:
    """The grid of a run whose frames have ``indices`` (frame numbers, by position): one row per
    condition, or one row named ``all frames`` for a run of one scene; frames a condition names but
    the run lacks are left out."""
    where = {int(index): p for p, index in enumerate(indices)}
    conditions = condition_rows(results)
    if not conditions:
        every = [r for r in headline_rows(results) if r["split"] == "all frames"]
        return [GridRow("all frames", False, list(range(len(indices))), every[0] if every else {})]
    blocks = results.get("conditions") or []
    return [GridRow(str(row["condition"]), bool(row["held_out"]),
                    [where[int(f)] for f in block.get("frames") or [] if int(f) in where], row)
            for row, block in zip(conditions, blocks)]


def _parts(row: GridRow, most: int) -> list[GridRow]:
    """``row`` cut into rows of at most ``most`` frames, each named with the views it holds."""
    if len(row.positions) <= most:
        return [row]
    return [GridRow(f"{row.name} (views {i}–{min(i + most, len(row.positions)) - 1})", row.held_out,
                    row.positions[i:i + most], row.numbers) for i in range(0, len(row.positions), most)]


def page_of(rows: list[GridRow], page: int, per_page: int) -> tuple[list[GridRow], int]:
    """Page ``page`` (from 1, clamped to the pages there are) of ``rows`` holding at most ``per_page``
    frames, whole conditions where they fit (a longer row is cut into pages of its own); and the
    number of pages."""
    pages: list[list[GridRow]] = [[]]
    count = 0
    for row in (part for r in rows for part in _parts(r, per_page)):
        if pages[-1] and count + len(row.positions) > per_page:
            pages.append([])
            count = 0
        pages[-1].append(row)
        count += len(row.positions)
    return pages[min(max(page, 1), len(pages)) - 1], len(pages)


def thumb_size(height: int, width: int) -> tuple[int, int]:
    """The CSS size (w, h) a frame of height × width pixels is shown at in the grid: its long side
    about :data:`THUMB_PX` (small frames enlarged by a whole factor, large ones shrunk)."""
    side = max(height, width, 1)
    scale = THUMB_PX // side if side <= THUMB_PX else THUMB_PX / side
    return max(1, round(width * scale)), max(1, round(height * scale))


def columns(n: int, thumb_w: int, width: int = CELLS_W) -> int:
    """How many thumbnails of ``thumb_w`` px go across a row of ``n``: as many as ``width`` holds, the
    lines then filled evenly (24 views in 12 + 12, not 15 + 9), so views line up across rows."""
    most = max(1, width // (thumb_w + CELL_EXTRA))
    lines = -(-max(n, 1) // most)
    return -(-max(n, 1) // lines)


def verdict(row: Mapping[str, Any], task: str) -> tuple[bool | None, str, str]:
    """(still right?, a short cell text, a longer one) for the victim's verdict on one frame (a
    results.json per-frame row): a classifier's class and confidence, a detector's detected or
    missed, its best box's score, and when missed the class of its best box."""
    score = row.get("score")
    shown = "" if score is None else f"{float(score):.2f}"
    if task == "detection":
        ok = row.get("detected")
        ok = None if ok is None else bool(ok)
        mark = {True: "✓", False: "✗", None: "?"}[ok]
        boxes = row.get("boxes") or []
        seen = boxes[0].get("label") if boxes and isinstance(boxes[0], Mapping) else None
        short = f"{mark} {seen}" if ok is False and seen else f"{mark} {shown.lstrip('0')}"
        best = f"{seen} {shown}" if seen else shown or "–"
        return ok, short, f"{'detected' if ok else 'missed'}, best box {best}"
    ok = row.get("correct")
    ok = None if ok is None else bool(ok)
    mark = {True: "✓", False: "✗", None: "?"}[ok]
    short = f"{mark} {shown.lstrip('0')}" if ok else f"{mark} {row.get('class')}"
    return ok, short, f"{mark} {row.get('class')} {shown}".strip()


def success_text(numbers: Mapping[str, Any]) -> str:
    """``benign → adversarial · success`` of a grid row, in %."""
    def pct(v: Any) -> str:
        return "–" if v is None else f"{100.0 * float(v):.0f} %"
    rate = numbers.get("success_rate")
    return (f"{pct(numbers.get('benign'))} → <b>{pct(numbers.get('adversarial'))}</b>"
            f"{'' if rate is None else f'<br>fooled {pct(rate)}'}")


def _cell(frame: "FrameData", side: "Side", task: str, view: str, size: tuple[int, int],
          link: str) -> str:
    ok, short, long = verdict(side.row, task)
    state = {True: "ok", False: "no", None: "na"}[ok]
    split = "h" if frame.held_out else "a"
    title = f"frame {frame.index} · {'held-out' if frame.held_out else 'attacked'} · {view}: {long}"
    return (f'<a class="cell {split} {state}" href="{escape(link)}" title="{escape(title)}" '
            f'style="width:{size[0]}px">'
            f'<img src="thumbs/{view}/frame_{frame.index:04d}.png" width={size[0]} height={size[1]} '
            f'alt="{view} frame {frame.index}" loading="lazy"><span>{escape(short)}</span></a>')


def grid_html(rows: list[GridRow], frames: list["FrameData"], task: str) -> str:
    """The report's grid: per row its name, held-out tag and numbers, the adversarial thumbnails, and
    the benign row shown when its link is followed (``#benign-N``: CSS ``:target``, no script)."""
    if not frames:
        return "<p class=meta>(no frames)</p>"
    h, w = frames[0].adversarial.image.shape[:2]
    size = thumb_size(h, w)
    across = columns(max(len(r.positions) for r in rows) if rows else 1, size[0])
    style = f'style="grid-template-columns:repeat({across},max-content)"'
    out = ["<div class=grid>"]
    for i, row in enumerate(rows):
        chosen = [frames[p] for p in row.positions]
        tag = '<span class="tag held">held out</span>' if row.held_out else ""
        link = lambda f: f"frames/frame_{f.index:04d}.png"  # noqa: E731
        adv = "".join(_cell(f, f.adversarial, task, "adversarial", size, link(f)) for f in chosen)
        ben = "".join(_cell(f, f.benign, task, "benign", size, link(f)) for f in chosen)
        out.append(
            f'<div class=cond id="row-{i}"><div class=cname><b>{escape(row.name)}</b> {tag}<br>'
            f'<span class=meta>{success_text(row.numbers)}</span><br>'
            f'<a href="#benign-{i}">benign row</a></div>'
            f'<div class=cells {style}>{adv}</div>'
            f'<div class="cells benign" id="benign-{i}" {style}>{ben}'
            f'<a class=close href="#row-{i}">hide the benign row</a></div>'
            "</div>")
    return "".join(out) + "</div>"


GRID_CSS = """
.grid{margin:6px 0}.cond{display:grid;grid-template-columns:150px 1fr;gap:2px 8px;border-top:1px solid #e4e4e4;
padding:4px 0}.cname{font-size:12px;line-height:1.35;overflow-wrap:anywhere}.cells{display:grid;gap:3px;justify-content:start}
.cell{display:block;border:3px solid #1f6fb2;text-decoration:none;font-size:11px;line-height:13px;text-align:center;
color:#222}.cell.h{border-color:#e9a03b}.cell img{display:block}
.cell span{display:block;overflow:hidden;text-overflow:ellipsis;white-space:nowrap;margin:0 auto}
.cell.ok span{color:#1a7f37}.cell.no span{color:#c81e2d;font-weight:600}
.cells.benign{display:none;grid-column:2;background:#f6f6f6;padding:3px}.cells.benign:target{display:grid}
.close{font-size:12px;grid-column:1/-1}.cell img{image-rendering:pixelated}.tag.held{background:#e9a03b}
"""
