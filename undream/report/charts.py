"""The report's charts as PNG bytes, each with a caption naming the command that made it.

The loss chart and the texture pictures are the dashboard's own
(:mod:`undream.charts`, :mod:`undream.dashboard.images`); the
sweep's chart adds what the dashboard's lacks: one line per attack *and*
split (attacked, held-out) with mean ± standard deviation over seeds.
Metric values are fractions in [0, 1], drawn as %; ε in 0–255 sRGB units.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from undream import charts as dash_charts
from undream.report.pictures import texture_png as hatched_png
from undream.report.data import RunData
from undream.report.draw import INK, PAPER, caption_png, decode_png, encode_png, font, with_caption
from undream.report.tables import SPLIT_NAMES, Point, metric_name

LOSS_UNITS = {"ce": "nats", "targeted_ce": "nats", "margin": "logits"}  # every other loss is unitless
SPLIT_STYLE = {"attacked": "-", "held_out": "--"}


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


def _series_label(key: tuple[str, ...], split: str) -> str:
    return f"{' '.join(key)}, {SPLIT_NAMES[split]}"


def eps_png(series: dict[tuple[str, ...], list[Point]], metric: str | None, command: str) -> bytes:
    """Adversarial metric (%) against ε, one line per series and split; error bars: ± one standard
    deviation over the seeds of a point (none with one seed)."""
    fig, ax = dash_charts.new_figure()
    name = metric_name(metric)
    for (key, points), color in zip(series.items(), dash_charts.COLORS * 4):
        for split in SPLIT_STYLE:
            pts = [p for p in points if p.split == split and p.mean is not None]
            if not pts:
                continue
            ax.errorbar([p.eps for p in pts], [100.0 * p.mean for p in pts],  # type: ignore[operator]
                        yerr=[100.0 * (p.std or 0.0) for p in pts], color=color, linestyle=SPLIT_STYLE[split],
                        marker="o" if split == "attacked" else "s", markersize=4, capsize=3, linewidth=1.3,
                        label=_series_label(key, split))
    if series:
        ax.legend(fontsize=7, frameon=False)
    else:
        dash_charts.empty_axes(ax, "no run of this sweep has results")
    ax.set_ylim(-5, 105)
    ax.xaxis.get_major_locator().set_params(integer=False)
    ax.set_xlabel("ε (0–255 sRGB units)", fontsize=9)
    ax.set_ylabel(f"adversarial {name} (%)", fontsize=9)
    ax.set_title(f"adversarial {name} against ε (mean ± std over seeds)", fontsize=10)
    return caption_png(dash_charts.figure_png(fig), made_by(command))


def chart_metric(rows: list[dict[str, Any]]) -> str | None:
    """The one metric of the rows (accuracy or ap50), None when mixed or none."""
    found = {r.get("metric") for r in rows if r.get("metric")}
    return found.pop() if len(found) == 1 else None
