"""The report's charts as PNG bytes, each with a caption naming the command that made it.

The loss chart and the texture pictures are the dashboard's own
(:mod:`undream.charts`, :mod:`undream.dashboard.images`); a sweep's charts
add what the dashboard's lacks: one chart per metric (a split's adversarial
value, attack success) with every seed shown and its spread.
Metric values are fractions in [0, 1], drawn as %; ε in 0–255 sRGB units.
"""
from __future__ import annotations

from pathlib import PurePath
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from undream import charts as dash_charts
from undream.report.pictures import texture_png as hatched_png
from undream.report.data import RunData
from undream.report.draw import INK, PAPER, caption_png, decode_png, encode_png, font, with_caption
from undream.report.compare import Cell, Comparison, numeric_x
from undream.report.tables import metric_name

LOSS_UNITS = {"ce": "nats", "targeted_ce": "nats", "margin": "logits"}  # every other loss is unitless
X_LABELS = {"attack.eps": "ε (0–255 sRGB units)"}
TRANSFER_IN = (0.9, 0.24)  # the transfer chart's height in inches: axes and labels, and per row


def made_by(command: str) -> str:
    return f"made by: {command}"


def loss_png(data: RunData, command: str) -> bytes:
    """Mean attack loss per iteration (the dashboard's chart) with the command as caption."""
    kind = data.run.run_config.loss
    png = dash_charts.loss_chart(data.iterations, f"{kind}, {LOSS_UNITS.get(kind, 'unitless')}")
    return caption_png(png, made_by(command))


def unseen_count(data: RunData) -> tuple[int, int] | None:
    """(texels no frame sees, texels) of the texture; None when visibility is unknown."""
    mask = data.seen.mask
    return None if mask is None else (int((~mask).sum()), int(mask.size))


def unseen_sentence(data: RunData) -> str:
    """How the unseen texels were found, how many, and how many of them the attack changed anyway."""
    counts = unseen_count(data)
    if counts is None or data.seen.mask is None:
        return data.seen.how + "."
    changed = np.any(data.texture_final != data.texture0, axis=2)
    stray = int((changed & ~data.seen.mask).sum())
    return (f"{data.seen.how}. {counts[0]} of {counts[1]} texels are unseen; the attack changed {stray} of "
            "them (a sampled pass can miss texels that few pixels see).")


def _difference(data: RunData) -> np.ndarray:
    """|final − T0| per texel (max over RGB), scaled so that ε is white: H×W×3 sRGB in [0, 1]."""
    eps = data.run.run_config.attack.eps
    diff = np.abs(data.texture_final - data.texture0).max(axis=2) * 255.0 / max(eps, 1e-6)
    return np.repeat(np.clip(diff, 0.0, 1.0)[..., None], 3, axis=2)


def texture_png(data: RunData, command: str) -> bytes:
    """Initial texture, final texture and their difference side by side, unseen texels hatched."""
    mask = data.seen.mask
    panels = [("initial (T0, benign)", data.texture0), ("final (adversarial)", data.texture_final),
              ("|final − T0| (white: ε)", _difference(data))]
    pictures = [decode_png(hatched_png(t, mask)) for _, t in panels]
    h, w = pictures[0].shape[:2]
    sheet = Image.new("RGB", (3 * w + 4 * 10, h + 50), PAPER)
    draw = ImageDraw.Draw(sheet)
    for i, ((title, _), pic) in enumerate(zip(panels, pictures)):
        sheet.paste(Image.fromarray(pic), (10 + i * (w + 10), 28))
        draw.text((10 + i * (w + 10), 8), title, fill=INK, font=font(12))
    counts = unseen_count(data)
    legend = ("unseen texels: unknown (see the page)" if counts is None else
              f"magenta hatching: texels no frame sees ({counts[0]} of {counts[1]})")
    draw.text((10, h + 32), legend, fill=INK, font=font(11))
    return encode_png(with_caption(sheet, made_by(command)))


def compare_png(comparison: Comparison, metric: str, command: str) -> bytes:
    """One metric of a sweep (%) against the grid's x, one series per attack (and other non-seed
    values): each cell's mean over seeds joined by a line, its min–max as an error bar and each seed
    as a dot; the mean benign value as a grey dashed line."""
    fig, ax = dash_charts.new_figure()
    by_series: dict[str, list[Cell]] = {}
    for cell in comparison.cells.get(metric, []):
        by_series.setdefault(cell.series, []).append(cell)
    numeric = numeric_x(comparison)
    ticks = list(dict.fromkeys(c.x for cells in comparison.cells.values() for c in cells))
    span = (max(map(float, ticks)) - min(map(float, ticks)) or 1.0) if numeric and ticks else float(len(ticks) or 1)
    for i, ((name, cells), color) in enumerate(zip(by_series.items(), dash_charts.COLORS * 4)):
        shift = 0.012 * span * (i - (len(by_series) - 1) / 2)  # series side by side, not on top of each other
        pts = [c for c in cells if c.values]
        if not pts:
            continue  # no run of this series has finished
        xs = [(float(c.x) if numeric else ticks.index(c.x)) + shift for c in pts]
        means = [100.0 * c.mean for c in pts]  # type: ignore[operator]
        bars = [[m - 100.0 * min(c.values) for m, c in zip(means, pts)],
                [100.0 * max(c.values) - m for m, c in zip(means, pts)]]
        ax.errorbar(xs, means, yerr=bars, color=color, marker="o", markersize=4, capsize=3, linewidth=1.3,
                    label=name)
        seeds = [(x, 100.0 * v) for x, c in zip(xs, pts) for v in c.values]
        ax.scatter(*zip(*seeds), color=color, s=9, alpha=0.55, zorder=3, linewidths=0)
    if metric in comparison.benign:
        ax.axhline(100.0 * comparison.benign[metric], color="#999", linestyle="--", linewidth=1, label="benign")
    if by_series:
        ax.legend(fontsize=7, frameon=False)
    else:
        dash_charts.empty_axes(ax, "no run of this sweep has finished")
    if not numeric:
        ax.set_xticks(range(len(ticks)), [str(t) for t in ticks])
    ax.set_ylim(-5, 105)
    if numeric:
        ax.xaxis.get_major_locator().set_params(integer=False)
    ax.set_xlabel(X_LABELS.get(comparison.x_axis or "", comparison.x_axis or "(seeds only)"), fontsize=9)
    ax.set_ylabel("attack success (%)" if metric == "success" else f"adversarial {comparison.metric_name} (%)",
                  fontsize=9)
    ax.set_title(f"{comparison.title(metric)} ({comparison.finished} of {comparison.total} runs finished)",
                 fontsize=10)
    return caption_png(dash_charts.figure_png(fig), made_by(command))


def _transfer_label(row: dict[str, Any], n: int) -> str:
    """``this run`` or ``[n] scene (condition) · victim · sim`` with the scene's file name only."""
    if n == 0:
        return "this run"
    scene = PurePath(str(row["scene"])).stem or str(row["scene"])
    condition = f" ({row['condition']})" if row.get("condition") else ""
    return f"[{n}] {scene}{condition} · {row['victim']} · {row['sim']}"


def transfer_png(rows: list[dict[str, Any]], command: str) -> bytes:
    """The transfer table's rows (:func:`undream.report.transfer.transfer_rows`) as grouped bars: per
    row, benign and adversarial value (%) on all its frames, the run's own row first (at the top)."""
    fig, ax = dash_charts.new_figure()
    sources = list(dict.fromkeys(r["source"] for r in rows))
    shown = [(r, (r.get("all") or (None, None, None))) for r in rows]
    height = TRANSFER_IN[0] + TRANSFER_IN[1] * len(rows)
    fig.set_size_inches(dash_charts.SIZE_IN[0] * 1.25, height)
    fig.subplots_adjust(left=0.42, right=0.97, bottom=0.55 / height, top=1 - 0.3 / height)
    ys = np.arange(len(shown))[::-1].astype(float)
    for offset, side, color, name in ((0.19, 0, "#9a9a9a", "benign"), (-0.19, 1, dash_charts.COLORS[1], "adversarial")):
        values = [100.0 * v[side] if v[side] is not None else np.nan for _, v in shown]  # none: no bar
        ax.barh(ys + offset, values, height=0.36, color=color, label=name)
    ax.set_yticks(ys, [_transfer_label(r, sources.index(r["source"])) for r, _ in shown], fontsize=7)
    ax.yaxis.grid(False)
    names = sorted({metric_name(r.get("metric")) for r in rows})
    ax.set_xlim(0, 100)
    ax.set_xlabel(f"{' / '.join(names)} on all frames (%)", fontsize=9)
    ax.legend(fontsize=7, frameon=False, loc="lower right", ncols=2, bbox_to_anchor=(1.0, 1.0))
    return caption_png(dash_charts.figure_png(fig), made_by(command))
