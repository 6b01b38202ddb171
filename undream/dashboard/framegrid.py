"""The run page's frames a page at a time: the report's grid (conditions down, views across) as plain
data for the template, the conditions table, and the frame pairs shown full size (no HTTP here).

A page holds whole conditions, about :data:`FRAMES_PER_PAGE` frames
(:func:`undream.report.grid.page_of`; a run of one scene is one row, paged
the same way); ``?page=N`` picks it. Each thumbnail links to its frame's
pair (benign and adversarial at 256 px, a detector's boxes over them):
``?frame=F`` shows that one; without it, a page of at most
:data:`PAIRS_SHOWN` frames shows all its pairs.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

from undream.dashboard.errors import BadRequest
from undream.report.data import held_out_indices
from undream.report.grid import THUMB_PX, GridRow, columns, grid_rows, page_of, success_text, thumb_size, verdict
from undream.report.tables import condition_rows, weakest_first

if TYPE_CHECKING:
    from undream.store import Store

FRAMES_PER_PAGE = 96  # frames of the grid (and rows of the job grid) on one page
PAIRS_SHOWN = 8  # a page with at most this many frames shows every pair full size
MOST_ACROSS = 32  # thumbnails in a line at most: dashboard.css has a class .x1 … .x32 for each count
# (the dashboard's Content-Security-Policy allows no inline style)


def check_number(name: str, value: str | None, lowest: int = 1) -> int | None:
    """A whole-number query parameter (None when absent), or BadRequest naming it."""
    if value in (None, ""):
        return None
    try:
        number = int(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        number = lowest - 1
    if number < lowest:
        raise BadRequest(f"{name} {value!r}: must be a whole number from {lowest}")
    return number


def _short(pred: Mapping[str, Any] | None, task: str) -> tuple[bool | None, str, str]:
    """The grid's verdict on one evaluation prediction (:func:`undream.report.grid.verdict`)."""
    if not pred:
        return None, "–", "no frame yet"
    if task == "detection":
        scores = pred.get("scores") or []
        row = {"detected": pred.get("detected"), "score": max(scores) if scores else None,
               "boxes": sorted(pred.get("detections") or [], key=lambda d: -float(d.get("score") or 0))}
    else:
        row = {"correct": pred.get("correct"), "class": pred.get("name") or f"class {pred.get('label')}",
               "score": pred.get("score")}
    return verdict(row, task)


def _cells(row: GridRow, frames: Mapping[int, Mapping[str, Any]], held: set[int], indices: list[int],
           task: str) -> list[dict[str, Any]]:
    cells = []
    for p in row.positions:
        pred = (frames.get(p) or {}).get("adversarial")
        ok, short, long = _short(pred, task)
        split = "held-out" if row.held_out or indices[p] in held else "attacked"
        cells.append({"frame": p, "index": indices[p], "held_out": split == "held-out", "has": bool(pred),
                      "state": {True: "ok", False: "no", None: "na"}[ok], "short": short,
                      "title": f"frame {indices[p]} · {split} · adversarial: {long}"})
    return cells


def frame_size(store: "Store", run_id: str) -> tuple[int, int] | None:
    """(height, width) of the run's evaluation frames (the first one there is), None before any."""
    run = store.get_run(run_id)
    for phase in ("adversarial", "pre"):
        for job in store.jobs(run_id, run.iteration, phase):
            if job.status == "succeeded" and job.image_ref:
                h, w = store.blobs.get_array(job.image_ref).shape[:2]
                return int(h), int(w)
    return None


def frames_view(run: Mapping[str, Any], results: Mapping[str, Any] | None, page: int | None,
                frame: int | None, size: tuple[int, int] | None = None) -> dict[str, Any]:
    """What the run page's frame sections show: ``rows`` of this page (name, held out, the numbers as
    HTML, ``cells``), ``page`` and ``pages``, ``positions`` (this page's frame positions, for the job
    grid), ``pairs`` (the frame rows shown full size), ``conditions`` (most fooled first, each with
    the page that holds it), ``chosen`` (``frame``) and ``thumb``, the CSS size (w, h) of a
    thumbnail of a frame of ``size`` (height, width; 64 × 64 when unknown), and ``across``, the
    thumbnails in a line (:func:`undream.report.grid.columns`).

    ``run``: :func:`undream.dashboard.query.run_detail`; ``results``: the run's results.json (None
    before the evaluation).
    """
    res = results or {}
    n = int(run["n_frames"])
    per_frame = (res.get("benign") or {}).get("per_frame") or []
    indices = [int(r["frame"]) for r in per_frame] if len(per_frame) == n else list(range(n))
    task = str(res.get("task") or ("detection" if any("boxes" in (f.get("adversarial") or f.get("benign") or {})
                                                       for f in run["frames"]) else "classification"))
    rows = grid_rows(res, indices) if res else [GridRow("all frames", False, list(range(n)), {})]
    if frame is not None and not 0 <= frame < n:
        raise BadRequest(f"frame {frame}: the run has frames 0 to {n - 1}")
    if page is None and frame is not None:  # the page that holds the chosen frame
        page = next((i for i in range(1, len(rows) + 1)
                     if frame in {p for r in page_of(rows, i, FRAMES_PER_PAGE)[0] for p in r.positions}), 1)
    shown, pages = page_of(rows, page or 1, FRAMES_PER_PAGE)
    if page is not None and page > pages:
        raise BadRequest(f"page {page}: the run's frames fill {pages} page{'s' if pages != 1 else ''}")
    by_frame = {int(f["frame"]): f for f in run["frames"]}
    thumb = thumb_size(*(size or (THUMB_PX, THUMB_PX)))
    held = held_out_indices(dict(res))
    positions = [p for r in shown for p in r.positions]
    page_of_row = {r.name: i for i in range(1, pages + 1) for r in page_of(rows, i, FRAMES_PER_PAGE)[0]}
    conditions = condition_rows(res)
    order = {c["condition"]: i for i, c in enumerate(conditions)}
    if frame is not None:
        pairs = [by_frame[frame]] if frame in by_frame else []
    else:
        pairs = [by_frame[p] for p in positions if p in by_frame] if len(positions) <= PAIRS_SHOWN else []
    return {
        "rows": [{"name": r.name, "held_out": r.held_out, "numbers": success_text(r.numbers) if r.numbers else "",
                  "cells": _cells(r, by_frame, held, indices, task), "id": f"row-{rows.index(r)}"} for r in shown],
        "page": min(max(page or 1, 1), pages), "pages": pages, "positions": positions, "pairs": pairs,
        "chosen": frame, "task": task, "n_frames": n, "thumb": thumb,
        "across": min(MOST_ACROSS, columns(max((len(r.positions) for r in shown), default=1), thumb[0])),
        "conditions": [{**c, "page": page_of_row.get(c["condition"], 1), "id": f"row-{order[c['condition']]}"}
                       for c in weakest_first(conditions)],
    }
