"""The report's HTML: one self-contained page per run and per sweep (inline CSS, no JS, no network).

Pictures and CSV files are named by relative links to files next to the
page. Every value from a run (names, config, classes) is escaped.
"""
from __future__ import annotations

import json
from html import escape
from typing import Any, Collection, Mapping

from undream.redact import redact
from undream.report.compare import Cell, Comparison
from undream.report.data import RunData
from undream.report.grid import GRID_CSS, grid_html, grid_rows
from undream.report.sheet import ATTACKED_RGB, HELD_OUT_RGB
from undream.report.tables import metric_name, weakest_first
from undream.report.transfer import transfer_html

CSS = """
body{font:14px/1.45 system-ui,sans-serif;color:#222;margin:24px auto;max-width:1320px;padding:0 16px}
h1{font-size:22px;margin:0 0 4px}h2{font-size:17px;margin:28px 0 8px;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:6px 0}td,th{border:1px solid #ddd;padding:3px 8px;text-align:left}
th{background:#f4f4f4}td{white-space:nowrap}table.compact td,table.compact th{padding:1px 6px}td.wrap{white-space:normal;overflow-wrap:anywhere;max-width:420px}td.n{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:10px 0}figcaption{color:#555;font-size:13px;max-width:900px}
code,pre{font:12px ui-monospace,monospace;background:#f6f6f6}pre{padding:8px;overflow:auto}
.meta{color:#555}.tag{display:inline-block;padding:0 6px;color:#fff;border-radius:3px}
img{max-width:100%}.pair{display:flex;gap:16px;align-items:flex-start}
.charts{display:flex;flex-wrap:wrap;gap:0 16px}.charts figure{flex:0 1 560px}
.pair figure{min-width:0}.pair .loss{flex:0 0 40%}.pair .tex{flex:1 1 0}summary{cursor:pointer;color:#555}
""" + GRID_CSS


def rgb(colour: tuple[int, int, int]) -> str:
    return "#%02x%02x%02x" % colour


def fmt(value: Any, percent: bool = False) -> str:
    """A table cell: – for None, % for metric fractions, 4 significant digits for other floats."""
    if value is None or value == "":
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{100.0 * value:.1f} %" if percent else f"{value:.4g}"
    return str(value)


def table(rows: list[dict[str, Any]], percent: Collection[str] = (), links: Mapping[str, str] | None = None,
          link_column: str = "") -> str:
    """An HTML table of ``rows``; columns in ``percent`` shown as %, ``link_column`` cells linked."""
    if not rows:
        return "<p class=meta>(none)</p>"
    cols = list(rows[0])
    head = "".join(f"<th>{escape(c)}</th>" for c in cols)
    body = []
    for row in rows:
        cells = []
        for c in cols:
            text = escape(fmt(row.get(c), c in percent))
            if c == link_column and links and row.get(c) in links:
                text = f'<a href="{escape(links[row[c]])}">{text}</a>'
            num = isinstance(row.get(c), (int, float)) and not isinstance(row.get(c), bool)
            cells.append(f"<td{' class=n' if num else ''}>{text}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def figure(src: str, alt: str, caption: str, command: str, cls: str = "") -> str:
    attr = f' class="{escape(cls)}"' if cls else ""
    return (f'<figure{attr}><img src="{escape(src)}" alt="{escape(alt)}"><figcaption>{caption} '
            f"Made by <code>{escape(command)}</code>.</figcaption></figure>")


def document(title: str, body: str) -> str:
    return (f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>'
            f"<style>{CSS}</style></head><body>{body}</body></html>\n")


def _success_cell(row: dict[str, Any]) -> str:
    rate = row.get("success_rate")
    if rate is None:
        return f"n/a ({row.get('n_eligible') or 0} frames right before the attack)"
    return f"{100.0 * rate:.1f} % ({row.get('n_success')} of {row.get('n_eligible')})"


def _metric_header(rows: list[dict[str, Any]]) -> str:
    """``accuracy: benign → adversarial`` (the rows' one metric), or plain when they differ."""
    names = {metric_name(r.get("metric")) for r in rows if r.get("metric")}
    return f"{escape(names.pop())}: benign → adversarial" if len(names) == 1 else "benign → adversarial"


def headline_table(rows: list[dict[str, Any]]) -> str:
    """Split | frames (a count: the frame numbers are in headline.csv) | benign → adversarial | success."""
    out = [f"<table id=headline><tr><th>split</th><th>frames</th><th>{_metric_header(rows)}</th>"
           "<th>attack success (fooled of the frames right before)</th></tr>"]
    for r in rows:
        out.append(f"<tr><td>{escape(r['split'])}</td><td class=n>{int(r['n_frames'])}</td>"
                   f"<td class=n>{fmt(r['benign'], True)} → <b>{fmt(r['adversarial'], True)}</b></td>"
                   f"<td>{escape(_success_cell(r))}</td></tr>")
    return "".join(out) + "</table>"


def _meta(data: RunData) -> str:
    res, attack = data.results, data.results.get("attack") or {}
    wall = (res.get("wall_time_seconds") or {}).get("wall")
    return (f"<p class=meta>run <code>{escape(data.run.id)}</code> · victim <code>{escape(str(res.get('victim')))}"
            f"</code> ({escape(data.task)}) · object class <b>{escape(data.label)}</b> · attack "
            f"{escape(str(attack.get('name')))}, ε = {escape(fmt(attack.get('eps')))} (0–255 sRGB), "
            f"{escape(fmt(attack.get('steps')))} steps · {len(data.frames)} frames · wall time "
            f"{escape(fmt(wall))} s</p>")


def _legend() -> str:
    return (f'<span class=tag style="background:{rgb(ATTACKED_RGB)}">attacked</span> frames the attack '
            f'optimised on; <span class=tag style="background:{rgb(HELD_OUT_RGB)}">held-out</span> frames it '
            "never rendered for a gradient.")


def _grid_legend(data: RunData, conditions: list[dict[str, Any]] | None) -> str:
    verdict = ("✓ detected / ✗ missed and the best box score" if data.task == "detection" else
               "✓ still the object's class and the confidence / ✗ the class it took the object for")
    rows = ("One row per condition, in the run's order (views across)" if conditions else
            "Every frame of the run, in order")
    return (f"<p class=meta>{rows}: the adversarial frames, each framed by its split: {_legend()} "
            f"Under each, the victim's verdict ({verdict}; hover for more). A frame opens full size: benign "
            "and adversarial side by side, enlarged, with the victim's prediction"
            f"{' and its boxes' if data.task == 'detection' else ''}. <i>benign row</i> shows a row's benign "
            "frames for comparison.</p>")


def conditions_table(rows: list[dict[str, Any]]) -> str:
    """A multi-condition run's transfer, most fooled first (:func:`~undream.report.tables.weakest_first`):
    condition | attacked or held out | frames | benign → adversarial | attack success."""
    out = [f"<table id=conditions class=compact><tr><th>condition (most fooled first)</th><th></th>"
           f"<th>frames</th><th>{_metric_header(rows)}</th><th>attack success</th></tr>"]
    for r in weakest_first(rows):
        out.append(f"<tr><td>{escape(r['condition'])}</td><td>{'held out' if r['held_out'] else 'attacked'}</td>"
                   f"<td class=n>{int(r['n_frames'])}</td>"
                   f"<td class=n>{fmt(r['benign'], True)} → <b>{fmt(r['adversarial'], True)}</b></td>"
                   f"<td>{escape(_success_cell(r))}</td></tr>")
    return "".join(out) + "</table>"


def run_body(data: RunData, headline: list[dict[str, Any]], unseen: str, command: str,
             conditions: list[dict[str, Any]] | None = None, moved: list[dict[str, Any]] | None = None) -> str:
    """The sections of a run's page (headline, conditions of a multi-condition run, the grid of frames,
    loss and texture, config)."""
    loss = data.run.run_config.loss
    transfer = [] if not conditions else [
        "<h2>Conditions</h2>", conditions_table(conditions),
        '<p class=meta>Every frame of each condition (scene) of the run, the conditions where the texture fooled '
        'the victim most first; a condition held out was never attacked: what the texture does where it was '
        'not optimised. In the run\'s order with frame numbers: <a href="conditions.csv">conditions.csv</a>.</p>']
    elsewhere = [] if not moved else [
        "<h2>Transfer: the texture elsewhere</h2>", transfer_html(moved),
        "<p class=meta>The run's own evaluation (first row) beside what <code>undream evaluate --json</code> "
        "measured of a texture on other scenes, conditions, victims or simulators (one row per file [n], scene "
        "and condition, victim, simulator and texture): benign → adversarial value and frames on every "
        "frame and on the frames a run would attack and hold out (its <code>--holdout</code>; the run's "
        'held-out frames are its held-out views and conditions together). <a href="transfer.csv">transfer.csv'
        "</a>.</p>",
        figure("transfer.png", "benign and adversarial value per evaluation",
               "Transfer at a glance: benign (grey) and adversarial (red) value on all frames of each row of the "
               "table, the run's own first.", command)]
    return "".join([
        f"<h1>Run {escape(data.run.name)}</h1>", _meta(data),
        "<h2>Headline</h2>", headline_table(headline),
        '<p class=meta>Held-out frames say whether the texture works beyond the views it was optimised on. '
        'Frame numbers of each split: <a href="headline.csv">headline.csv</a>; per frame (split'
        f'{", condition, view" if conditions else ""}, what the victim said): <a href="frames.csv">frames.csv</a>.</p>',
        *transfer, *elsewhere,
        "<h2>Frames</h2>", _grid_legend(data, conditions),
        grid_html(grid_rows(data.results, [f.index for f in data.frames]), data.frames, data.task),
        '<div class=pair>',
        figure("loss.png", "attack loss per iteration",
               f"Loss per iteration: the mean {escape(loss)} loss over the frames of each attack step (maximised "
               "by the attack); red points: steps that dropped a frame with a non-finite gradient.", command, "loss"),
        figure("texture.png", "initial and final texture",
               f"Texture: the benign texture T0, the adversarial texture that was evaluated (both 8-bit sRGB) "
               f"and their largest per-channel difference (white: ε). Unseen texels (hatched in magenta): "
               f"{escape(unseen)}", command, "tex"),
        "</div>",
        "<h2>Config</h2>", f"<details><summary>the run's config (JSON)</summary>"
        f"<pre>{escape(json.dumps(redact(data.run.config), indent=1, sort_keys=True))}</pre></details>",
    ])


def _grid(spec: Mapping[str, Any]) -> str:
    grid = spec.get("grid") or {}
    return "; ".join(f"{escape(str(k))} ∈ {escape(json.dumps(v))}" for k, v in grid.items()) or "(none)"


def _arrow(row: Mapping[str, Any], prefix: str) -> str:
    return f"{fmt(row.get(prefix + 'benign'), True)} → {fmt(row.get(prefix + 'adversarial'), True)}"


def compact_rows(rows: list[dict[str, Any]], grid: list[str]) -> list[dict[str, Any]]:
    """The results table as shown on the page: benign → adversarial per split in one cell each, an
    unfinished run's status with the attack steps it took."""
    return [{"run": r["run"], "name": r["name"], **{k: r.get(k) for k in grid},
             "status": r["status"] if r["status"] == "done" else f"{r['status']} (step {r.get('steps_done')})",
             "metric": metric_name(r.get("metric")) if r.get("metric") else None,
             "attacked: benign → adv.": _arrow(r, "attacked_"), "held-out: benign → adv.": _arrow(r, "held_out_"),
             "held-out success": r.get("held_out_success_rate"), "final loss": r.get("final_loss")}
            for r in rows]


def progress(side: Comparison) -> str:
    """How many of the sweep's runs finished, and what the others are doing (one sentence)."""
    others = ", ".join(f"{n} {status}" for status, n in sorted(side.statuses.items()) if status != "done")
    if not others:
        return f"All {side.total} runs finished."
    return (f"{side.finished} of {side.total} runs finished ({others}): the charts and the table show the finished "
            "runs only, a cell's seeds are its finished runs; the results table lists every run with its status.")


def _spread(cell: Cell) -> str:
    if not cell.values:
        return f"– <span class=meta>(0 of {cell.runs})</span>"
    sd = "" if cell.std is None else f" ± {100.0 * cell.std:.1f}"
    seeds = f"{len(cell.values)}" if len(cell.values) == cell.runs else f"{len(cell.values)} of {cell.runs}"
    return f"{100.0 * cell.mean:.1f}{sd} % <span class=meta>({seeds})</span>"  # type: ignore[operator]


def comparison_table(side: Comparison) -> str:
    """One row per cell (series, x), one column per metric: mean ± sample sd over seeds (seeds)."""
    metrics = list(side.cells)
    head = "".join(f"<th>{escape(side.title(m))}</th>" for m in metrics)
    x_name = escape(side.x_axis or "")
    rows = []
    for i, first in enumerate(side.cells[metrics[0]]):
        cells = "".join(f"<td class=n>{_spread(side.cells[m][i])}</td>" for m in metrics)
        x = f"<td class=n>{escape(fmt(first.x))}</td>" if side.x_axis else ""
        rows.append(f"<tr><td>{escape(first.series)}</td>{x}{cells}</tr>")
    return (f"<table id=comparison class=compact><tr><th>series</th>{f'<th>{x_name}</th>' if x_name else ''}"
            f"{head}</tr>{''.join(rows)}</table>")


def _compare_section(side: Comparison, command: str) -> list[str]:
    seeds = " and ".join(side.seed_axes) or "none (one run per cell: no spread)"
    status = [f"<h2>Runs side by side</h2><p class=meta>{escape(progress(side))} x: "
              f"{escape(side.x_axis or '(none)')}; series: {escape(', '.join(side.series_axes) or 'the attack')}; "
              f"seeds (the spread): {escape(seeds)}.</p>"]
    if not side.cells:
        return status + ["<p class=meta>No run of this sweep has finished yet: its charts and table come with the "
                         "first finished run.</p>"]
    charts = "".join(
        figure(f"compare_{m}.png", side.title(m),
               f"{escape(side.title(m))} (%) per cell: the mean over seeds (line), min–max (bar) and each seed "
               "(dot); grey dashed: the benign value (mean over the finished runs).", command)
        for m in side.cells)
    return status + [
        f"<div class=charts>{charts}</div>", comparison_table(side),
        "<p class=meta>Each cell: mean ± one sample standard deviation over its seeds, in %, and (the seeds: "
        "its finished runs, of its runs when some have not finished). Every cell with its min, max and "
        'values: <a href="comparison.csv">comparison.csv</a>.</p>']


def sweep_body(sweep: Any, rows: list[dict[str, Any]], side: Comparison, links: Mapping[str, str],
               command: str) -> str:
    """The sections of a sweep's page (the runs side by side, the results table, the runs)."""
    unfinished = [r for r in rows if r["run"] not in links]
    return "".join([
        f"<h1>Sweep {escape(sweep.name)}</h1>",
        f"<p class=meta>sweep <code>{escape(sweep.id)}</code> · {len(rows)} runs · grid: {_grid(sweep.spec)}</p>",
        *_compare_section(side, command),
        "<h2>Results per run</h2>",
        table(compact_rows(rows, [str(k) for k in sweep.spec.get("grid") or {}]), {"held-out success"},
              links, "run"),
        '<p class=meta>Metric values in %; success: fooled of the held-out frames the victim got right before '
        'the attack; final loss in the run\'s loss. Every column (all frames too) in '
        '<a href="results.csv">results.csv</a>.</p>',
        "<h2>Runs</h2><ul>",
        "".join(f'<li><a href="{escape(links[r["run"]])}">{escape(r["name"])}</a> ({escape(r["run"])}): '
                f"{escape(fmt(r.get('held_out_adversarial'), True))} held-out adversarial</li>"
                for r in rows if r["run"] in links),
        "".join(f"<li>{escape(r['name'])} ({escape(r['run'])}): {escape(r['status'])}: no page (a page needs a "
                "finished run)</li>"
                for r in unfinished),
        "</ul>",
    ])
