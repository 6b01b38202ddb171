"""Generated `undream evaluate` command lines (hostile textures, output files, holdouts) and races
for one output, and what undream does with each (issue 41's fuzz).

``evaluate`` cases: a texture file drawn from valid and broken ``.npy`` and ``.png`` files (every
dtype, shape and channel count, NaN and out-of-range values, cut short, random bytes, headers
claiming huge sizes or far too long, 16-bit and transparent PNGs, another size than the scene's),
``--json``/``--csv`` drawn from new files and things that must never be replaced (the texture, the
scene's files, a user's file, a FIFO, a symbolic link, a folder, a folder that does not exist, one
file for both), and ``--holdout`` drawn from valid and broken forms. :func:`judge_evaluate` runs it
in-process (click's runner) in a work folder: exit 0 leaves every input byte-identical and writes
whole JSON/CSV (an explicit output may replace a user's regular file, never an input, a FIFO or a
link); anything else is exit 2 with one line naming the texture, the scene, the option or
its value, and every byte on disk as it was.

Race cases: 2–6 threads claim one new output folder (``claim_output`` with a run's or a baseline's
marker) or replace one file (``atomic_write``) at once. :func:`judge_race`: at most one claim wins,
every loser is a one-line SpecError, the folder then holds the winner's marker alone (or nothing
when none won); a raced file holds one writer's bytes whole and no temporary file is left.
Used by ``tests/test_fuzz_inputs.py`` and ``scripts/fuzz_inputs.py``.
"""
from __future__ import annotations

import io
import json
import os
import shutil
import struct
import threading
import traceback
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import strategies as st

from fuzz_cli import changed, fingerprint

SIZE = (8, 16)  # H, W of the fuzz scene's texture (tests/farm_support.make_scene)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png(width: int, height: int, depth: int, colour: int, raw: bytes) -> bytes:
    """A PNG written by hand (colour 0 grey, 2 RGB, 4 grey+alpha, 6 RGBA), any header, any data."""
    head = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", head) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b"")


def _png_of(array: np.ndarray) -> bytes:
    """``array`` (H×W or H×W×C, uint8 or uint16) as a PNG of its own depth and channels."""
    channels = 1 if array.ndim == 2 else array.shape[2]
    depth = 16 if array.dtype == np.uint16 else 8
    rows = b"".join(b"\0" + row.astype(">u2" if depth == 16 else "u1").tobytes()
                    for row in array.reshape(array.shape[0], -1))
    return png(array.shape[1], array.shape[0], depth, {1: 0, 2: 4, 3: 2, 4: 6}[channels], rows)


def _npy_header(header: str, data: bytes = b"") -> bytes:
    text = header + " " * (63 - (10 + len(header)) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode() + data


@st.composite
def textures(draw: Any) -> tuple[str, str, bytes]:
    """(how it was made, suffix, bytes) of a texture file, valid or broken."""
    how = draw(st.sampled_from(["valid npy", "valid uint8 npy", "valid png", "grey png", "16-bit png",
                                "rgba png", "other size", "shape", "dtype", "values", "cut short",
                                "random bytes", "huge header", "long header", "bomb png", "empty"]))
    h, w = SIZE
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if how == "valid npy":
        return how, ".npy", _npy(rng.random((h, w, 3)).astype(draw(st.sampled_from([np.float32, np.float64]))))
    if how == "valid uint8 npy":
        return how, ".npy", _npy(rng.integers(0, 256, (h, w, 3)).astype(np.uint8))
    if how == "valid png":
        return how, ".png", _png_of(rng.integers(0, 256, (h, w, 3)).astype(np.uint8))
    if how == "grey png":
        return how, ".png", _png_of(rng.integers(0, 256, (h, w)).astype(np.uint8))
    if how == "16-bit png":
        shape = draw(st.sampled_from([(h, w), (h, w, 3)]))
        return how, ".png", _png_of(rng.integers(0, 65536, shape).astype(np.uint16))
    if how == "rgba png":
        alpha = draw(st.sampled_from([255, 0, 128]))
        rgba = rng.integers(0, 256, (h, w, 4)).astype(np.uint8)
        rgba[..., 3] = alpha
        return how, ".png", _png_of(rgba)
    if how == "other size":
        hh, ww = draw(st.integers(1, 40)), draw(st.integers(1, 40))
        suffix = draw(st.sampled_from([".npy", ".png"]))
        data = rng.integers(0, 256, (hh, ww, 3)).astype(np.uint8)
        return how, suffix, _npy(data) if suffix == ".npy" else _png_of(data)
    if how == "shape":
        shape = tuple(draw(st.lists(st.integers(0, 20), min_size=0, max_size=4)))
        return how, ".npy", _npy(np.zeros(shape, np.float32))
    if how == "dtype":
        dtype = draw(st.sampled_from(["f2", "i1", "i4", "u2", "i8", "bool", "c8", "U1", "V4"]))
        return how, ".npy", _npy(np.zeros((h, w, 3), dtype))
    if how == "values":
        bad = draw(st.sampled_from([np.nan, np.inf, -np.inf, -0.5, 1.5, 1e30]))
        array = rng.random((h, w, 3)).astype(np.float32)
        array.flat[draw(st.integers(0, array.size - 1))] = bad
        return how, ".npy", _npy(array)
    if how == "cut short":
        suffix = draw(st.sampled_from([".npy", ".png"]))
        data = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
        whole = _npy(data) if suffix == ".npy" else _png_of(data)
        return how, suffix, whole[:draw(st.integers(1, len(whole) - 1))]
    if how == "random bytes":
        return how, draw(st.sampled_from([".npy", ".png"])), draw(st.binary(min_size=1, max_size=300))
    if how == "huge header":
        dims = draw(st.lists(st.integers(0, 10**12), min_size=3, max_size=3))
        return how, ".npy", _npy_header(f"{{'descr': '<f4', 'fortran_order': False, 'shape': ({dims[0]}, "
                                        f"{dims[1]}, 3), }}", b"\0" * 64)
    if how == "long header":
        return how, ".npy", _npy_header("{'descr': '<f4', 'fortran_order': False, 'shape': (8, 16, 3), }"
                                        + " " * draw(st.integers(10_000, 65_000)))
    if how == "bomb png":
        side = draw(st.integers(8193, 100_000))
        return how, ".png", png(side, side, 8, 2, b"\0" * 100)
    return how, draw(st.sampled_from([".npy", ".png"])), b""


USER_FILE = '{"mine": true}\n'
OUTPUTS = ["", "new.json", "new.csv", "TEXTURE", "SCENE/sequence.json", "SCENE/metadata.json",
           "thesis/results.json", "fifo", "link.json", "thesis", "nowhere/rows.json", "new.json"]
HOLDOUTS = ["auto", "none", "{every: 2}", "{every: 1}", "{every: 2, offset: 1}", "{frames: [0]}",
            "{frames: [9]}", "{frames: []}", "evry", "[1, 2]", "{evry: 2}", "", "{every: 10000000}"]


@dataclass
class EvaluateCase:
    how: str  # how the texture was made (see :func:`textures`)
    suffix: str
    data: bytes
    json_out: str  # one of OUTPUTS ("": not given)
    csv_out: str
    holdout: str


@st.composite
def evaluate_cases(draw: Any) -> EvaluateCase:
    how, suffix, data = draw(textures())
    return EvaluateCase(how, suffix, data, draw(st.sampled_from(OUTPUTS)), draw(st.sampled_from(OUTPUTS)),
                        draw(st.sampled_from(HOLDOUTS)))


def make_evaluate_work(root: Path, scene: Path) -> Path:
    """The work folder of the evaluate cases: a copy of the scene, a user's folder, a FIFO and a
    symbolic link to a user's file."""
    root.mkdir(parents=True)
    shutil.copytree(scene, root / "scene")
    (root / "thesis").mkdir()
    (root / "thesis" / "results.json").write_text(USER_FILE)
    os.mkfifo(root / "fifo")
    (root / "link.json").symlink_to(root / "thesis" / "results.json")
    return root


def _target(name: str, work: Path, texture: Path) -> str | None:
    if not name:
        return None
    if name == "TEXTURE":
        return str(texture)
    return str(work / name.replace("SCENE", "scene"))


def judge_evaluate(case: EvaluateCase, work: Path, runner: Any) -> str:
    """Run ``case`` in ``work``; ``ok`` / ``refused`` or ``FAIL: why`` (see the module docstring)."""
    from undream.cli import main

    texture = work / f"texture{case.suffix}"
    texture.write_bytes(case.data)
    json_out, csv_out = _target(case.json_out, work, texture), _target(case.csv_out, work, texture)
    argv = ["evaluate", str(texture), str(work / "scene"), "--victim", "bundled:classifier", "--spp", "1",
            "--holdout", case.holdout]
    argv += ["--json", json_out] if json_out else []
    argv += ["--csv", csv_out] if csv_out else []
    before = fingerprint(work)
    written = {p for p in (json_out, csv_out) if p and not Path(p).exists()}
    named = {p for p in (json_out, csv_out) if p}  # may be written: a new file, or a user's file asked for
    try:
        result = runner.invoke(main, argv, catch_exceptions=True)
        return _evaluate_verdict(result, before, work, texture, named, json_out, csv_out)
    finally:
        texture.unlink(missing_ok=True)
        for p in written:
            Path(p).unlink(missing_ok=True)
        (work / "thesis" / "results.json").write_text(USER_FILE)


def _evaluate_verdict(result: Any, before: dict[str, str], work: Path, texture: Path, named: set[str],
                      json_out: str | None, csv_out: str | None) -> str:
    """Exit 0 may write the files named by --json and --csv (a new file, or a regular file that is
    no input: an explicit output replaces it) and nothing else: the texture, the scene, the FIFO and
    the symbolic link's target stay byte-identical."""
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        tb = "".join(traceback.format_exception(result.exception)[-4:])
        return f"FAIL: traceback {type(result.exception).__name__}: {str(result.exception)[:300]}\n{tb[-3000:]}"
    after = fingerprint(work)
    left = changed(before, after)
    if result.exit_code == 0:
        stray = [k for k in left if str(work / k) not in named]
        if stray:
            return f"FAIL: exit 0 but changed files it must not: {stray[:5]}"
        try:
            if json_out:
                assert json.loads(Path(json_out).read_text())["rows"]
            if csv_out and csv_out != json_out:
                assert Path(csv_out).read_text().startswith("scene,")
        except (OSError, ValueError, KeyError, AssertionError) as err:
            return f"FAIL: exit 0 but an output is not whole: {err!r}"
        return "ok"
    lines = result.stderr.strip().splitlines()
    if result.exit_code != 2 or len(lines) != 1 or not lines[0].startswith("undream: error: "):
        return f"FAIL: exit {result.exit_code}, {len(lines)} line(s): {result.stderr[-2000:]!r}"
    if left:
        return f"FAIL: refused ({lines[0][:300]}) but changed the disk: {left[:5]}"
    names = (str(texture), str(work / "scene"), "--json", "--csv", "--holdout", "holdout")
    if not any(n in lines[0] for n in names):
        return f"FAIL: the error names neither the texture, the scene nor an option: {lines[0][:500]!r}"
    return "refused"


@dataclass
class RaceCase:
    what: str  # "claim" (an output folder) or "replace" (one file)
    start: str  # the folder or file beforehand: "absent", "empty" (folder) / "old" (file)
    markers: tuple[str, ...]  # per thread: "metadata.json" (a run) or "baseline.json" (a baseline)


@st.composite
def race_cases(draw: Any) -> RaceCase:
    n = draw(st.integers(2, 6))
    if draw(st.booleans()):
        return RaceCase("claim", draw(st.sampled_from(["absent", "empty"])),
                        tuple(draw(st.sampled_from(["metadata.json", "baseline.json"])) for _ in range(n)))
    return RaceCase("replace", draw(st.sampled_from(["absent", "old"])), ("",) * n)


def judge_race(case: RaceCase, work: Path) -> str:
    """Run ``case``'s threads at once (a barrier) in a fresh folder under ``work``; ``ok`` or ``FAIL``."""
    from scheduler.preflight import claim_output
    from undream.errors import SpecError
    from undream.spec.io import atomic_write
    from undream.spec.run import RunConfig

    place = work / f"race-{os.getpid()}-{threading.get_ident()}"
    shutil.rmtree(place, ignore_errors=True)
    place.mkdir(parents=True)
    target = place / ("out" if case.what == "claim" else "results.json")
    if case.start == "empty":
        target.mkdir()
    elif case.start == "old":
        target.write_text("old")
    config = RunConfig.from_json({"name": "race", "scene": str(place), "victim": "bundled:classifier"})
    barrier = threading.Barrier(len(case.markers))
    outcomes: list[Any] = [None] * len(case.markers)

    def one(i: int) -> None:
        barrier.wait()
        try:
            if case.what == "claim":
                claim_output(target, config, marker=case.markers[i],
                             command="run" if case.markers[i] == "metadata.json" else "baseline")
            else:
                atomic_write(target, f"writer {i} " * 1000)
            outcomes[i] = "won"
        except SpecError as err:
            outcomes[i] = err
        except BaseException as err:  # noqa: BLE001 - judged below, never swallowed silently
            outcomes[i] = err

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(case.markers))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    try:
        return _race_verdict(case, target, outcomes)
    finally:
        shutil.rmtree(place, ignore_errors=True)


def _race_verdict(case: RaceCase, target: Path, outcomes: list[Any]) -> str:
    from undream.errors import SpecError

    odd = [o for o in outcomes if o != "won" and not isinstance(o, SpecError)]
    if odd:
        return f"FAIL: {type(odd[0]).__name__}: {odd[0]}"
    if case.what == "replace":
        text = target.read_text()
        if outcomes.count("won") != len(outcomes) or not any(text == f"writer {i} " * 1000 for i in range(len(outcomes))):
            return f"FAIL: the raced file holds {text[:40]!r}…, no writer's whole bytes"
        left = sorted(p.name for p in target.parent.iterdir())
        return "ok" if left == ["results.json"] else f"FAIL: files left beside it: {left}"
    winners = [i for i, o in enumerate(outcomes) if o == "won"]
    losers = [o for o in outcomes if isinstance(o, SpecError)]
    if len(winners) > 1:
        return f"FAIL: {len(winners)} commands claimed one folder"
    if any("\n" in str(e) or "another command claimed this folder" not in str(e) for e in losers):
        return f"FAIL: a loser's message: {losers[0]}"
    held = sorted(p.name for p in target.iterdir()) if target.is_dir() else []
    want = [case.markers[winners[0]]] if winners else []
    if held != want:
        return f"FAIL: the folder holds {held}, not {want}"
    return "ok"
