"""The report's tables as rows of plain data, and CSV text (no drawing, no HTML here).

Metric values are fractions in [0, 1] (accuracy, or AP at IoU 0.5), ε in
0–255 sRGB units, losses the run's loss (``ce`` in nats). Splits:
``attacked`` (frames the attack optimised on), ``held_out`` (never rendered
for a gradient) and ``all``.
"""
from __future__ import annotations

import csv
import io
from typing import TYPE_CHECKING, Any, Mapping

from scheduler.query import result_rows
from undream.report.data import SPLITS, RunData

if TYPE_CHECKING:
    from undream.store import RunSnapshot, SweepSnapshot

SPLIT_NAMES = {"attacked": "attacked frames", "held_out": "held-out frames",
               "held_out_conditions": "held-out conditions", "all": "all frames"}


def metric_name(metric: str | None) -> str:
    return {"accuracy": "accuracy", "ap50": "AP@0.5"}.get(metric or "", metric or "metric")


def _value(block: Mapping[str, Any] | None) -> float | None:
    value = (block or {}).get("value")
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _split_block(results: Mapping[str, Any], split: str) -> dict[str, Any] | None:
    """A results.json split block (``all`` from the top-level numbers), None when empty."""
    if split != "all":
        return results.get(split) or None
    frames = [row.get("frame") for row in (results.get("benign") or {}).get("per_frame") or []]
    return {"frames": frames, "benign": results.get("benign"), "adversarial": results.get("adversarial"),
            "attack_success": (results.get("attack_success") or {}).get("aggregate") or {}}


def headline_rows(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per split: frames, metric, benign → adversarial value, and attack success (fooled of the
    frames the victim got right before the attack)."""
    rows = []
    for split in (*SPLITS, "held_out_conditions", "all"):
        block = _split_block(results, split)
        if block is not None:
            rows.append({"split": SPLIT_NAMES[split], **_block_row(block)})
    return rows


def _block_row(block: Mapping[str, Any]) -> dict[str, Any]:
    success = block.get("attack_success") or {}
    return {"n_frames": len(block.get("frames") or []), "frames": " ".join(str(f) for f in block.get("frames") or []),
            "metric": (block.get("benign") or {}).get("metric"),
            "benign": _value(block.get("benign")), "adversarial": _value(block.get("adversarial")),
            "success_rate": success.get("success_rate"), "n_success": success.get("n_success"),
            "n_eligible": success.get("n_eligible")}


def condition_rows(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """A multi-condition run's transfer: per condition (attacked, or held out whole), its frames,
    benign → adversarial value and attack success, in the run's order; [] for a run of one scene."""
    return [{"condition": c["name"], "held_out": bool(c.get("held_out")), **_block_row(c)}
            for c in results.get("conditions") or []]


def weakest_first(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``rows`` (:func:`condition_rows`) most fooled first: highest attack success, then lowest
    adversarial value; rows without a success rate (no frame right before the attack) last."""
    def key(row: dict[str, Any]) -> tuple[Any, ...]:
        rate, adv = row.get("success_rate"), row.get("adversarial")
        return (rate is None, -(rate or 0.0), 2.0 if adv is None else adv, str(row.get("condition")))
    return sorted(rows, key=key)


def condition_of(results: Mapping[str, Any]) -> dict[int, tuple[str, int]]:
    """Frame index → (its condition's name, its view: its place in the condition, from 0); {} for a
    run of one scene."""
    return {int(f): (str(c["name"]), view) for c in results.get("conditions") or []
            for view, f in enumerate(c.get("frames") or [])}


def frame_rows(data: RunData) -> list[dict[str, Any]]:
    """Per frame: split (a multi-condition run's: condition and view too) and what the victim said on
    the benign and on the adversarial render."""
    rows = []
    where = condition_of(data.results)
    for f in data.frames:
        row: dict[str, Any] = {"frame": f.index, "split": "held-out" if f.held_out else "attacked"}
        if where:
            row["condition"], row["view"] = where.get(f.index, (None, None))
        for name, side in (("benign", f.benign), ("adversarial", f.adversarial)):
            r = side.row
            if data.task == "detection":
                row.update({f"{name}_detected": r.get("detected"), f"{name}_n_detections": r.get("n_detections")})
            else:
                row.update({f"{name}_class": r.get("class"), f"{name}_correct": r.get("correct")})
            row[f"{name}_score"] = r.get("score")
        rows.append(row)
    return rows


def sweep_rows(sweep: "SweepSnapshot", runs: list["RunSnapshot"]) -> list[dict[str, Any]]:
    """One row per run of the sweep (:func:`scheduler.query.result_rows`), with the split numbers and the
    attack steps taken (``steps_done``, k/N) added."""
    rows = result_rows(sweep.spec, runs)
    for row, run in zip(rows, runs):
        res = run.results or {}
        for split in SPLITS:
            block = res.get(split) or {}
            row[f"{split}_benign"] = _value(block.get("benign"))
            row[f"{split}_adversarial"] = _value(block.get("adversarial"))
        row["held_out_success_rate"] = ((res.get("held_out") or {}).get("attack_success") or {}).get("success_rate")
        row["steps_done"] = f"{run.iteration}/{run.run_config.attack.steps}"  # attack steps taken
    return rows


def to_csv(rows: list[dict[str, Any]]) -> str:
    """The rows as CSV text (header from the first row; None as an empty cell)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["run"], lineterminator="\n")
    writer.writeheader()
    writer.writerows([{k: "" if v is None else v for k, v in row.items()} for row in rows])
    return buf.getvalue()
