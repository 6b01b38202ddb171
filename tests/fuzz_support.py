"""Malformed specs and run configs, generated, and what ``undream`` does with each.

Inputs start from a valid trajectory spec or run config and are broken the
way users break them: a field deleted, an unknown field added, a value of the
wrong type or an extreme number put anywhere (NaN, ±inf, 1e308, 2⁶³, huge
strings, nested lists), the file cut short, or bytes that are not text at
all. Each input goes through the real command line in-process
(``undream init SPEC --check`` / ``undream run RUN --check``, click's test
runner), which runs every check the real command makes before writing.

:func:`outcome` classifies what happened; an input may work (exit 0) or be
refused (exit 2 with one line that names the input file), and must leave the
folder exactly as it was. Anything else (a traceback, several lines, a
message that does not name the file, a file written) is a failure.
Used by ``tests/test_fuzz_inputs.py`` (300 inputs) and
``scripts/fuzz_inputs.py`` (as many as asked, with a table of outcomes).
"""
from __future__ import annotations

import copy
import json
import math
import re
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from hypothesis import strategies as st

SPEC: dict[str, Any] = {
    "name": "fuzz", "seed": 0, "frames": 2, "fps": 2,
    "camera": {"fov": 40, "resolution": [16, 16], "path": {"type": "orbit", "center": [0, 0.5, 0],
                                                           "radius": 3, "height": 1.2, "start_deg": 0,
                                                           "end_deg": 90},
               "look_at": "object"},
    "object": {"asset": {"name": "ball", "mesh": "builtin:sphere",
                         "texture": {"resolution": [16, 8], "uv_scale": 1, "init": [0.5, 0.5, 0.5]}},
               "path": {"type": "static", "position": [0, 0, 0]}, "yaw": 15},
    "actors": [],
    "environment": {"weather": "clear", "time_of_day": 15.5, "background": "plain"},
}

# The same with an extra actor and the environment given per frame.
SPEC_ACTORS: dict[str, Any] = {
    **SPEC, "actors": [{"asset": {"name": "cone", "mesh": "builtin:traffic_cone"},
                        "path": {"type": "dolly", "start": [1, 0, -1], "end": [1, 0, 1]}}],
    "environment": [{"weather": "fog", "time_of_day": 9}, {"weather": "night", "time_of_day": 22}]}


# Keyframed camera and object paths (cubic and linear, look_at, yaw and rotation keys).
SPEC_KEYS: dict[str, Any] = {
    **SPEC, "frames": 3,
    "camera": {"fov": 50, "resolution": [16, 12],
               "path": {"type": "keyframes", "interpolation": "cubic",
                        "keys": [{"frame": 0, "position": [0, 1, 4], "look_at": [0, 0.5, 0]},
                                 {"frame": 2, "position": [2, 1.5, 3], "look_at": [0, 0.4, 0]}]}},
    "object": {"asset": {"name": "ball", "mesh": "builtin:sphere", "scale": 0.5},
               "path": {"type": "keyframes", "interpolation": "linear",
                        "keys": [{"frame": 0, "position": [0, 0, 0], "yaw": 0},
                                 {"frame": 2, "position": [0.5, 0, 0], "rotation": [0, 45, 0]}]}},
    "environment": {"weather": "cloudy", "time_of_day": 12}}


def json_bases() -> dict[str, dict[str, Any]]:
    """The JSON sources: a canonical sequence.json (of SPEC) and the repository's Unreal export."""
    from undream.scene.trajectory import sequence_from_trajectory

    root = Path(__file__).resolve().parents[1]
    return {"sequence.json": sequence_from_trajectory(SPEC).to_json(),
            "Unreal export": json.loads((root / "examples" / "unreal" / "drive_by_export.json").read_text())}


def run_doc(scene: str) -> dict[str, Any]:
    """A valid run config on ``scene`` (a scene directory or a spec file)."""
    return {"name": "fuzz", "scene": scene, "victim": "bundled:classifier", "loss": "ce",
            "attack": {"name": "pgd", "eps": 16, "steps": 2}, "sim_spp": 2, "grad_spp": 2,
            "eval_spp": 2, "seed": 0, "gradient": "auto", "transport_refresh": 5}


def conditions_doc(spec: str) -> dict[str, Any]:
    """A valid multi-condition run config on the spec file ``spec``: a 2 × 2 grid of weathers and
    camera heights, one condition held out."""
    return {**run_doc(spec), "conditions": {
        "grid": {"camera.path.height": [1.0, 1.4], "environment.weather": ["clear", "fog"]},
        "holdout": ["height_1p4-weather_fog"]}}


def sweep_doc(scene: str) -> dict[str, Any]:
    """A valid sweep file on ``scene``: two budgets × two seeds of :func:`run_doc`'s run."""
    return {"name": "fuzz", "base": run_doc(scene), "grid": {"attack.eps": [4, 8], "seed": [0, 1]}}


# -- generation ------------------------------------------------------------------------------------

EXTREMES = [0, -1, 1, 2**31, 2**63, -(2**63), 10**30, 1e308, -1e308, 1e-308, math.nan, math.inf,
            -math.inf, 0.5, -0.0, "", " ", "x" * 5000, "../../etc/passwd", "builtin:nope", "\x00", "é≈∂",
            True, False, None, [], {}, [[]], [None], [1e308, -1e308, 0]]
# Each kind of value equally likely (st.one_of leans towards its first, simplest branches).
scalars = st.sampled_from([st.none(), st.booleans(), st.integers(-(2**70), 2**70),
                           st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
                           st.sampled_from(EXTREMES)]).flatmap(lambda kind: kind)
values = st.sampled_from([scalars, scalars, st.lists(scalars, max_size=4),
                          st.dictionaries(st.text(max_size=6), scalars, max_size=3)]).flatmap(lambda kind: kind)


def paths(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path to a value inside ``doc`` (dict keys and list positions)."""
    out = [prefix] if prefix else []
    if isinstance(doc, dict):
        for key, value in doc.items():
            out += paths(value, prefix + (key,))
    elif isinstance(doc, list):
        for i, value in enumerate(doc):
            out += paths(value, prefix + (i,))
    return out


def _parent(doc: Any, path: tuple) -> Any:
    for step in path[:-1]:
        doc = doc[step]
    return doc


@st.composite
def mutated(draw: Any, base: dict[str, Any]) -> dict[str, Any] | list | Any:
    """``base`` with one to three edits: a value replaced, a field deleted or an unknown one added."""
    doc = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 3))):
        where = paths(doc)
        if not where or not isinstance(doc, dict):
            break
        depth = draw(st.sampled_from(sorted({len(p) for p in where})))  # shallow fields as often as deep
        path = draw(st.sampled_from([p for p in where if len(p) == depth]))
        parent = _parent(doc, path)
        op = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        if op == "replace":
            parent[path[-1]] = copy.deepcopy(draw(values))
        elif op == "delete" and isinstance(parent, dict):
            del parent[path[-1]]
        elif op == "add" and isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = copy.deepcopy(draw(values))
    return doc


@dataclass(frozen=True)
class Input:
    """One generated input file: what it is (for the table), its bytes, and the ``--out`` it meets."""

    kind: str  # "spec", "run" or "sweep"
    how: str  # "edited", "truncated", "binary", "not a mapping", or a text-level break (TEXT_BREAKS)
    data: bytes
    suffix: str = ".yaml"  # ".json": a canonical sequence or an Unreal export
    out: str = "absent"  # the --out folder beforehand: "absent", "user" (a user's files), "earlier" (a run's)
    force: bool = False  # --force given


def dump(doc: Any, suffix: str = ".yaml") -> bytes:
    if suffix == ".json":
        return json.dumps(doc).encode("utf-8")  # NaN and Infinity as JavaScript writes them
    return yaml.safe_dump(doc, allow_unicode=True, sort_keys=False).encode("utf-8")


# Breaks no mapping can express: written into the text of a valid file.
TEXT_BREAKS = ("duplicate key", "alias bomb", "deep nesting", "huge number")


def text_break(how: str, text: str, line: int, suffix: str) -> str:
    """``text`` broken ``how`` (see :data:`TEXT_BREAKS`) at (or after) its ``line``-th line."""
    lines = text.splitlines()
    line = line % len(lines)
    if how == "duplicate key":  # the line again (a key given twice; in a JSON object too)
        if suffix == ".json":
            return text.replace('{"', '{"name": 1, "name": 2, "', 1)
        return "\n".join(lines[:line + 1] + [lines[line]] + lines[line + 1:]) + "\n"
    if how == "alias bomb":  # a billion laughs: nine levels of nine aliases each
        bomb = ["lol0: &l0 [lol]"] + [f"lol{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, 10)]
        return "\n".join(bomb) + "\n" + text
    if how == "deep nesting":
        depth = 5000 + 1000 * line
        return text.replace("0", "[" * depth + "0" + "]" * depth, 1) if suffix == ".json" else \
            text + f"zzz: {'[' * depth}1{']' * depth}\n"
    # a number of thousands of digits, in place of a 0 that stands alone (not one inside a path:
    # a temporary folder's name holding a 0 made the scene's path the broken value)
    number = re.search(r"(?<![\w/.-])0(?![\w.])", text)
    at = number.start() if number else text.index("0")
    return text[:at] + "7" * (4400 + line) + text[at + 1:]


@st.composite
def inputs(draw: Any, kind: str, base: dict[str, Any], suffix: str = ".yaml") -> Input:
    """An input file of ``kind`` broken one of the ways in the module docstring, and the ``--out``
    folder it meets (absent, a user's folder, an earlier run's output; ``--force`` or not)."""
    how = draw(st.sampled_from(["edited"] * 6 + ["truncated", "binary", "not a mapping", *TEXT_BREAKS]))
    out, force = draw(st.sampled_from(["absent", "user", "earlier"])), draw(st.booleans())
    if how == "edited":
        data = dump(draw(mutated(base)), suffix)
    elif how == "truncated":
        text = dump(base, suffix)
        data = text[:draw(st.integers(0, len(text) - 1))]
    elif how == "binary":
        data = draw(st.binary(min_size=1, max_size=200))
    elif how == "not a mapping":
        data = dump(draw(st.one_of(st.lists(scalars, max_size=3), scalars)), suffix)
    else:
        data = text_break(how, dump(base, suffix).decode(), draw(st.integers(0, 50)), suffix).encode()
    return Input(kind, how, data, suffix, out, force)


# -- running one --------------------------------------------------------------------------------------


USER_FILES = {"thesis.tex": "years of work\n", "results.json": '{"mine": true}\n'}


def _prepare_out(out: Path, state: str) -> None:
    """Make ``out`` as ``state`` says: absent, a user's folder, or an earlier run's output folder."""
    if state == "absent":
        return
    out.mkdir()
    if state == "user":
        for name, text in USER_FILES.items():
            (out / name).write_text(text)
    else:
        (out / "metadata.json").write_text(json.dumps({"undream_output": "run", "status": "started"}))
        (out / "results.json").write_text('{"earlier": true}\n')


def outcome(item: Input, work: Path, runner: Any) -> str:
    """Run ``item`` through the command line in ``work``; ``ok`` / ``refused`` or ``FAIL: why``.

    First with ``--check``; an input that ``--check`` refuses is then given to the real command
    too, which must refuse it the same way. ``--out`` is prepared as ``item.out`` says, and
    every byte under ``work`` (the input file and ``--out`` included) must be as it was.
    """
    import shutil

    from fuzz_cli import fingerprint
    from undream.cli import main

    name = {"spec": f"spec{item.suffix}", "run": "run.yaml", "sweep": "sweep.yaml"}[item.kind]
    path, out = work / name, work / "out"
    path.write_bytes(item.data)
    _prepare_out(out, item.out)
    command = {"spec": "init", "run": "run", "sweep": "sweep"}[item.kind]
    argv = [command, str(path), "--out", str(out)] + (["--force"] if item.force and item.kind != "sweep" else [])
    if item.kind == "sweep":
        argv += ["--broker", "redis://127.0.0.1:1/0", "--database", f"sqlite:///{work}/farm.db",
                 "--blobs", str(work / "blobs")]
    before = fingerprint(work)
    try:
        verdict = _one(runner.invoke(main, argv + ["--check"], catch_exceptions=True), (path, out), before, work)
        if verdict == "refused":
            real = _one(runner.invoke(main, argv + ["--no-progress"] * (item.kind != "sweep"),
                                      catch_exceptions=True), (path, out), before, work)
            if real != "refused":
                verdict = f"FAIL: --check refused it, the command itself: {real}"
    finally:
        path.unlink(missing_ok=True)
        shutil.rmtree(out, ignore_errors=True)
    return verdict


def _one(result: Any, names: tuple[Path, Path], before: dict[str, str], work: Path) -> str:
    """What one invocation did: ``ok``, ``refused`` (one line naming the input file or ``--out``,
    nothing changed) or FAIL."""
    from fuzz_cli import changed, fingerprint

    left = changed(before, fingerprint(work))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        tb = "".join(traceback.format_exception(result.exception)[-4:])
        return f"FAIL: traceback {type(result.exception).__name__}: {str(result.exception)[:300]}\n{tb[-3000:]}"
    if left and result.exit_code != 0:
        return f"FAIL: refused but changed the disk: {left[:5]}"
    if left:
        return f"FAIL: --check wrote or changed files: {left[:5]}"
    if result.exit_code == 0:
        return "ok"
    lines = result.stderr.strip().splitlines()
    if result.exit_code != 2 or len(lines) != 1:
        return f"FAIL: exit {result.exit_code}, {len(lines)} line(s): {result.stderr[-2000:]!r}"
    if not lines[0].startswith("undream: error: ") or not any(str(p) in lines[0] for p in names):
        return f"FAIL: the error does not name the file {names[0]} (or --out): {lines[0][:500]!r}"
    return "refused"
