"""What ``undream evaluate`` measured elsewhere, beside a run's own numbers: the report's transfer table.

An evaluation file is what ``undream evaluate --json FILE`` writes:
``{"texture", "rows": [{scene, victim, sim, texture, split, frames, metric,
benign, adversarial}], "frames"}`` with metric values fractions in [0, 1] and
splits ``all``, ``attacked``, ``held_out`` and ``condition NAME`` (one per
condition of a multi-condition scene). The table has one row per (file,
scene, condition, victim, simulator, texture) with the splits across; its
first row is the run's own evaluation (results.json).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from html import escape
from pathlib import Path
from typing import Any, Mapping

from undream.errors import SpecError
from undream.report.tables import metric_name

SPLITS = ("all", "attacked", "held_out")
ROW_KEYS = ("scene", "victim", "split", "frames", "metric", "benign", "adversarial")


@dataclass(frozen=True)
class Evaluation:
    """One ``undream evaluate --json`` file: its name (as given), the texture it judged, its rows."""

    name: str
    texture: str
    rows: list[dict[str, Any]]


def _number(value: Any) -> bool:
    return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))


def load_evaluation(path: Path) -> Evaluation:
    """Read ``path``; SpecError naming the file and what is wrong when it is not such a file."""
    where = f"--evaluation {path}"
    try:
        data = json.loads(Path(path).read_text())
    except OSError as err:
        raise SpecError(f"{where}: cannot be read ({err.strerror or err})") from None
    except ValueError as err:
        raise SpecError(f"{where}: not JSON ({err})") from None
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list):
        raise SpecError(f"{where}: not the JSON of `undream evaluate --json` (no list of rows)")
    for i, row in enumerate(rows):
        missing = [k for k in ROW_KEYS if not isinstance(row, dict) or k not in row]
        if missing:
            raise SpecError(f"{where}: rows[{i}] lacks {', '.join(missing)} (written by `undream evaluate --json`?)")
        if not (_number(row["benign"]) and _number(row["adversarial"])):
            raise SpecError(f"{where}: rows[{i}]: benign and adversarial must be numbers, got "
                            f"{row['benign']!r} and {row['adversarial']!r}")
    return Evaluation(str(path), str(data.get("texture") or ""), rows)


def _run_row(results: Mapping[str, Any], config: Mapping[str, Any]) -> dict[str, Any]:
    """The run's own numbers as a transfer row (results.json's splits)."""
    row: dict[str, Any] = {"source": "this run (results.json)", "scene": str(config.get("scene") or ""),
                           "condition": "", "victim": str(results.get("victim") or config.get("victim") or ""),
                           "sim": str(config.get("sim") or "mitsuba"), "texture": "its final texture",
                           "metric": (results.get("benign") or {}).get("metric")}
    blocks = {"all": {"benign": results.get("benign"), "adversarial": results.get("adversarial"),
                      "frames": (results.get("benign") or {}).get("per_frame") or []},
              "attacked": results.get("attacked"), "held_out": _held_out(results)}
    for split, block in blocks.items():
        if block:
            n = block["frames"]
            row[split] = ((block.get("benign") or {}).get("value"), (block.get("adversarial") or {}).get("value"),
                          len(n) if isinstance(n, list) else n)
    return row


def _held_out(results: Mapping[str, Any]) -> dict[str, Any] | None:
    """Held-out frames as ``undream evaluate`` counts them: views and whole conditions together (its
    split ``held_out``); the run's held-out views alone when it held out no condition."""
    views, conditions = results.get("held_out"), results.get("held_out_conditions")
    if not conditions or not views:
        return views or conditions
    frames = {int(f) for block in (views, conditions) for f in block.get("frames") or []}
    value = {side: _accuracy((results.get(side) or {}).get("per_frame") or [], frames)
             for side in ("benign", "adversarial")}
    if value["benign"] is None or value["adversarial"] is None:
        return None  # a detector's AP of the union is not in results.json (the headline shows both apart)
    return {"frames": len(frames), "benign": {"value": value["benign"]}, "adversarial": {"value": value["adversarial"]}}


def _accuracy(per_frame: list[dict[str, Any]], frames: set[int]) -> float | None:
    """A classifier's accuracy over ``frames`` from results.json's per-frame rows; None for a detector's."""
    right = [r.get("correct") for r in per_frame if int(r.get("frame", -1)) in frames]
    if not right or any(not isinstance(v, bool) for v in right):
        return None
    return sum(right) / len(right)


def transfer_rows(results: Mapping[str, Any], config: Mapping[str, Any],
                  evaluations: list[Evaluation]) -> list[dict[str, Any]]:
    """The table's rows: the run's own first, then each file's, one per (scene, condition, victim,
    simulator, texture) with ``all`` / ``attacked`` / ``held_out`` as (benign, adversarial, frames)."""
    rows = [_run_row(results, config)]
    for ev in evaluations:
        pivot: dict[tuple[str, ...], dict[str, Any]] = {}
        for r in ev.rows:
            split = str(r["split"])
            condition = split[len("condition "):] if split.startswith("condition ") else ""
            key = (str(r["scene"]), condition, str(r["victim"]), str(r.get("sim") or ""), str(r.get("texture") or ""))
            row = pivot.setdefault(key, {"source": ev.name, "scene": key[0], "condition": condition,
                                         "victim": key[2], "sim": key[3], "texture": key[4], "metric": r["metric"]})
            row["all" if condition else split] = (r["benign"], r["adversarial"], r["frames"])
        rows.extend(pivot.values())
    return rows


def csv_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The table flattened for ``transfer.csv``: per split its benign and adversarial value and frames."""
    out = []
    for r in rows:
        flat = {k: r.get(k) for k in ("source", "scene", "condition", "victim", "sim", "texture", "metric")}
        for split in SPLITS:
            benign, adv, frames = r.get(split) or (None, None, None)
            flat.update({f"{split}_frames": frames, f"{split}_benign": benign, f"{split}_adversarial": adv})
        out.append(flat)
    return out


def _pct(value: Any) -> str:
    return "–" if value is None else f"{100.0 * float(value):.1f} %"


def _cell(value: Any) -> str:
    if not value:
        return "<td class=n>–</td>"
    benign, adv, frames = value
    return f"<td class=n>{_pct(benign)} → <b>{_pct(adv)}</b> <span class=meta>({frames})</span></td>"


def _legend(rows: list[dict[str, Any]], sources: list[str]) -> str:
    """Which file each row number is, and the texture it judged (when one per file)."""
    items = []
    for i, source in enumerate(sources[1:], 1):
        textures = sorted({r["texture"] for r in rows if r["source"] == source})
        judged = f": texture <code>{escape(textures[0])}</code>" if len(textures) == 1 else ""
        items.append(f"[{i}] <code>{escape(source)}</code>{judged}")
    return "<p class=meta>" + "; ".join(items) + ".</p>" if items else ""


def transfer_html(rows: list[dict[str, Any]]) -> str:
    """The table: where (the run, or [n] the n-th file; scene and condition, victim, simulator, and the
    texture when a file judged several), metric, then benign → adversarial (frames) on all, attacked
    and held-out frames; the files named under it."""
    sources = list(dict.fromkeys(r["source"] for r in rows))
    several = any(len({r["texture"] for r in rows if r["source"] == s}) > 1 for s in sources[1:])
    head = ("<table id=transfer class=compact><tr><th></th><th>scene (condition)</th><th>victim</th><th>sim</th>"
            f"{'<th>texture</th>' if several else ''}<th>metric</th><th>all frames</th><th>attacked</th>"
            "<th>held out</th></tr>")
    body = []
    for r in rows:
        n = sources.index(r["source"])
        scene = escape(r["scene"]) + (f" <b>({escape(r['condition'])})</b>" if r["condition"] else "")
        texture = f"<td class=wrap>{escape(r['texture'])}</td>" if several else ""
        body.append(f"<tr><td>{'this run' if n == 0 else f'[{n}]'}</td><td class=wrap>{scene}</td>"
                    f"<td>{escape(r['victim'])}</td><td>{escape(r['sim'])}</td>{texture}"
                    f"<td>{escape(metric_name(r['metric']))}</td>{''.join(_cell(r.get(s)) for s in SPLITS)}</tr>")
    return head + "".join(body) + "</table>" + _legend(rows, sources)
