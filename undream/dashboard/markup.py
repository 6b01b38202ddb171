"""The job grid as HTML, built in Python: a 64-frame × 100-iteration grid is 6400 cells, which
a Jinja loop renders in ~0.25 s and this in a tenth of that (every value escaped)."""
from __future__ import annotations

from typing import Any

from markupsafe import Markup, escape

from undream.dashboard.filters import duration

SMALL_COLUMNS = 16  # grids with at most this many columns ...
SMALL_ROWS = 32  # ... and rows write each job's seconds in its cell


def _column_name(column: str) -> str:
    return f"iteration {column}" if column.isdigit() else f"{column} evaluation"


def _title(frame: int, column: str, cell: dict[str, Any]) -> str:
    attempts = cell["attempts"]
    parts = [f"frame {frame}", _column_name(column), cell["status"], duration(cell["seconds"]),
             f"{attempts} attempt{'' if attempts == 1 else 's'}", f"worker {cell['worker'] or '–'}"]
    if cell["error"]:
        parts.append(f"error: {cell['error']}")
    return " · ".join(parts)


def _cell(frame: int, column: str, cell: dict[str, Any] | None, small: bool) -> str:
    if cell is None:
        return "<td></td>"
    classes = f"s-{cell['status']}" + (" slow" if cell["slow"] else "")
    text = f"{cell['seconds']:.2f}" if small and cell["seconds"] is not None else ""
    return f'<td class="{escape(classes)}" title="{escape(_title(frame, column, cell))}">{text}</td>'


def job_grid_html(grid: dict[str, Any], frames: list[int] | None = None) -> Markup:
    """The ``<table id="job-grid">`` of :func:`undream.dashboard.grid.job_grid`'s data: rows are
    frames (``frames``: only these positions, in this order; default every frame), columns iterations
    (every tenth labelled in big grids) then the evaluation; each cell's title says frame, iteration,
    status, seconds, attempts, worker and error."""
    columns = grid["columns"]
    chosen = range(len(grid["rows"])) if frames is None else [f for f in frames if 0 <= f < len(grid["rows"])]
    small = len(columns) <= SMALL_COLUMNS and len(chosen) <= SMALL_ROWS
    head = "".join(f"<th>{escape(c if c.isdigit() else c[:3]) if small or i % 10 == 0 or not c.isdigit() else ''}</th>"
                   for i, c in enumerate(columns))
    rows = [f"<tr><th>{f}</th>{''.join(_cell(f, columns[i], cell, small) for i, cell in enumerate(grid['rows'][f]))}"
            "</tr>" for f in chosen]
    return Markup(f'<table class="grid{" small" if small else ""}" id="job-grid"><thead><tr><th>frame</th>'
                  f'{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>')
