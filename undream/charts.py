"""Charts with axes and units, drawn on the server by matplotlib (PNG bytes), and sparkline points.

matplotlib's object API (a :class:`~matplotlib.figure.Figure` per chart, no
pyplot state) is safe to use from the server's threads. Every chart takes
plain data from :mod:`undream.dashboard.query` / :mod:`~undream.dashboard.sweeps`.
"""
from __future__ import annotations

import io
import math
from typing import Any, Sequence

SIZE_IN = (5.6, 2.7)  # width, height in inches
DPI = 100  # so a chart is 560×270 px
MARGINS = {"left": 0.115, "right": 0.98, "bottom": 0.165, "top": 0.9}  # of the figure: room for labels
TICKS = 7  # at most this many intervals between ticks per axis (each tick costs a few ms to draw)
BARS_UP_TO = 40  # more iterations than this: one filled step line instead of a bar each
COLORS = ("#1f6fb2", "#d1495b", "#2a9d8f", "#e9a03b", "#6a4c93", "#555555")


def warm_up() -> None:
    """Import matplotlib and draw one small chart (loads the fonts), once when a server starts."""
    fig, ax = new_figure()
    _title(ax, "warm-up")
    figure_png(fig)


def new_figure() -> tuple[Any, Any]:
    """A 560×270 px figure with one axes: fixed margins (measuring the labels' extents for a
    layout engine costs more than drawing the chart), a light grid, integer x ticks."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=SIZE_IN, dpi=DPI)
    fig.subplots_adjust(**MARGINS)
    ax = fig.add_subplot()
    ax.tick_params(labelsize=8)
    ax.xaxis.set_major_locator(MaxNLocator(nbins=TICKS, integer=True))
    ax.yaxis.set_major_locator(MaxNLocator(nbins=TICKS))
    ax.grid(True, color="#e4e4e4", linewidth=0.6)
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)
    return fig, ax


def _title(ax: Any, text: str) -> None:
    """The chart's title at a fixed height (placing it automatically measures every tick label)."""
    ax.set_title(text, fontsize=10, y=1.0, pad=6)


def figure_png(fig: Any) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    buf = io.BytesIO()
    FigureCanvasAgg(fig).print_png(buf)
    return buf.getvalue()


def empty_axes(ax: Any, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="#777", fontsize=9)


def loss_chart(iterations: Sequence[dict[str, Any]], loss_kind: str | None) -> bytes:
    """Mean loss over the kept frames per iteration; iterations that dropped frames marked in red."""
    fig, ax = new_figure()
    points = [(r["k"], r["loss_mean"]) for r in iterations if r["loss_mean"] is not None]
    if points:
        ks, ys = zip(*points)
        ax.plot(ks, ys, color=COLORS[0], linewidth=1.4, marker="o" if len(ks) < 40 else None, markersize=3)
        bad = [(r["k"], r["loss_mean"]) for r in iterations if r["n_bad"] and r["loss_mean"] is not None]
        if bad:
            ax.scatter(*zip(*bad), color=COLORS[1], zorder=3, s=14, label="frames dropped")
            ax.legend(fontsize=8, frameon=False)
    else:
        empty_axes(ax, "no iteration finished yet")
    ax.set_xlabel("iteration k (attack step)", fontsize=9)
    ax.set_ylabel(f"mean loss ({loss_kind or 'loss'})", fontsize=9)
    _title(ax, "attack loss per iteration (higher fools more)")
    return figure_png(fig)


def seconds_chart(iterations: Sequence[dict[str, Any]]) -> bytes:
    """Wall seconds per iteration (from one iteration record to the next; the first from the run's creation)."""
    fig, ax = new_figure()
    ks, seconds = [r["k"] for r in iterations], [r["seconds"] for r in iterations]
    if len(iterations) > BARS_UP_TO and ks == list(range(ks[0], ks[0] + len(ks))):
        ax.stairs(seconds, [k - 0.5 for k in ks] + [ks[-1] + 0.5], fill=True, color=COLORS[2])
    elif iterations:
        ax.bar(ks, seconds, color=COLORS[2], width=0.8)
    else:
        empty_axes(ax, "no iteration finished yet")
    ax.set_xlabel("iteration k", fontsize=9)
    ax.set_ylabel("wall time (s)", fontsize=9)
    _title(ax, "seconds per iteration")
    return figure_png(fig)


def _metric_name(metric: str | None) -> str:
    return {"accuracy": "accuracy", "ap50": "AP@0.5"}.get(metric or "", metric or "metric")


def _evaluation_points(ax: Any, evaluation: dict[str, Any], steps: int, name: str, spp: Any) -> bool:
    """The evaluation's benign (k = 0) and adversarial (k = N) values: the attacked and held-out
    frames apart when the run holds frames out, else every frame. Returns whether any was drawn."""
    splits = [(evaluation.get("attacked"), "attacked frames", "o", COLORS[0]),
              (evaluation.get("held_out"), "held-out frames", "^", COLORS[1])]
    groups = [(block, label, marker, color) for block, label, marker, color in splits if block]
    if not groups:
        groups = [(evaluation, "every frame", "s", COLORS[0])]
    drawn = False
    for block, label, marker, color in groups:
        points = [(x, 100.0 * v) for x, v in ((0, block.get("benign")), (steps, block.get("adversarial")))
                  if v is not None]
        if points:
            ax.scatter(*zip(*points), marker=marker, color=color, s=36, zorder=3, edgecolors="white",
                       label=f"{label}, evaluation at eval_spp {spp}: {name} "
                             + " → ".join(f"{y:.0f} %" for _, y in points))
            drawn = True
    return drawn


def metric_chart(data: dict[str, Any]) -> bytes:
    """Per iteration, the share (%) of the attacked frames the victim still classifies correctly (or
    detects) on the simulator's renders at ``sim_spp`` (``data["attacked"]``, from the attack jobs),
    and the evaluation's accuracy or AP@0.5 (%) at ``eval_spp`` before the attack (k = 0) and
    after it (k = N), the attacked and the held-out frames apart. ``data``: :func:`query.chart_data`."""
    fig, ax = new_figure()
    evaluation, steps = data["evaluation"], data.get("steps") or 1
    detector = evaluation.get("metric") == "ap50"
    line = data.get("attacked") or []
    if line:
        ks, ys = [p["k"] for p in line], [100.0 * p["value"] for p in line]
        ax.plot(ks, ys, color=COLORS[5], linewidth=1.3, marker="." if len(ks) < 40 else None,
                label=f"attacked frames, simulator renders at sim_spp {data.get('sim_spp')}: "
                      f"{'detected' if detector else 'correct'}")
    drawn = _evaluation_points(ax, evaluation, steps, _metric_name(evaluation.get("metric")), data.get("eval_spp"))
    if line or drawn:
        ax.legend(fontsize=6.5, loc="lower left", framealpha=0.85)
    else:
        empty_axes(ax, "no prediction stored yet (attack jobs keep them; the evaluation comes last)")
    ax.set_ylim(-5, 105)
    ax.set_xlim(-0.05 * steps, 1.05 * steps)
    ax.set_xlabel("iteration k (texture version; N: final texture)", fontsize=9)
    ax.set_ylabel("frames detected / AP (%)" if detector else "frames correct (%)", fontsize=9)
    _title(ax, "victim " + ("detection" if detector else "accuracy") + " per iteration")
    return figure_png(fig)


def sweep_chart(series: dict[str, list[dict[str, Any]]]) -> bytes:
    """Adversarial accuracy / AP@0.5 (%) against ε (0–255 sRGB units), one line per attack over every
    frame and a dashed one over the held-out frames (runs that hold frames out)."""
    fig, ax = new_figure()
    metrics = {p["metric"] for points in series.values() for p in points}
    for (attack, points), color in zip(series.items(), COLORS * 4):
        ax.plot([p["eps"] for p in points], [100.0 * p["adversarial"] for p in points], color=color,
                marker="o", markersize=4, linewidth=1.4, label=f"{attack}: every frame")
        held = [(p["eps"], 100.0 * p["held_out_adversarial"]) for p in points
                if p.get("held_out_adversarial") is not None]
        if held:
            ax.plot(*zip(*held), color=color, marker="^", markersize=4, linewidth=1.2, linestyle="--",
                    label=f"{attack}: held-out frames")
    benign = [p["benign"] for points in series.values() for p in points if p["benign"] is not None]
    if benign:
        ax.axhline(100.0 * sum(benign) / len(benign), color="#999", linestyle="--", linewidth=1,
                   label="benign (mean)")
    if series:
        ax.legend(fontsize=7, frameon=False, title="attack", title_fontsize=7)
    else:
        empty_axes(ax, "no run of this sweep has results yet")
    name = _metric_name(metrics.pop() if len(metrics) == 1 else None)
    ax.set_ylim(-5, 105)
    ax.set_xlabel("ε (0–255 sRGB units)", fontsize=9)
    ax.set_ylabel(f"adversarial {name} (%)", fontsize=9)
    _title(ax, f"adversarial {name} against ε")
    return figure_png(fig)


def sparkline(values: Sequence[float | None], width: int = 120, height: int = 24) -> str:
    """SVG polyline points ("x,y x,y ...") of the finite ``values`` scaled into width × height px."""
    pts = [(i, v) for i, v in enumerate(values) if v is not None and math.isfinite(v)]
    if len(pts) < 2:
        return ""
    lo, hi = min(v for _, v in pts), max(v for _, v in pts)
    span, last = (hi - lo) or 1.0, max(len(values) - 1, 1)
    return " ".join(f"{i * (width - 2) / last + 1:.1f},{height - 1 - (v - lo) * (height - 2) / span:.1f}"
                    for i, v in pts)
