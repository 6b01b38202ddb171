"""A detector's boxes, from results.json to the report and the dashboard: a real tiny `undream run`
against bundled:yolo (3 frames of 48 px, one attack step), `undream report` of it through the command
line, and its run page and JSON from the dashboard over the run's store.

results.json's per-frame rows hold the detector's kept boxes (at most 5, frame pixels, class names)
and the object's true box; the contact sheet draws them, the run page lays them over its frames,
and a run recorded before rows held boxes still makes a report and a run page.
"""
from __future__ import annotations

import html
import io
import json
import os
import re
import sqlite3
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from farm_support import make_scene, run_config, write_yaml

ROOT = Path(__file__).resolve().parents[1]
SIZE = 48  # px, every frame
SIDES = ("benign", "adversarial")


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("boxes")
    scene = make_scene(root / "scene", n_frames=3, size=SIZE)
    cfg = run_config(scene, "bundled:yolo", name="yolo", steps=1, loss="vanish", holdout="none")
    out = root / "out"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(root / "run.yaml", cfg)),
                          "--out", str(out), "--no-progress"], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert res.returncode == 0, res.stderr
    return {"root": root, "out": out, "results": json.loads((out / "results.json").read_text())}


def _report(target: Path, out: Path) -> list[np.ndarray]:
    """The report's full-size frame pictures (one row of the contact sheet each), in frame order."""
    from undream.cli import main

    res = CliRunner().invoke(main, ["report", str(target), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return [np.asarray(Image.open(p).convert("RGB")) for p in sorted((out / "frames").glob("frame_*.png"))]


def _data(folder: Path, work: Path):
    """The report's data of the run in ``folder`` (as `undream report FOLDER` reads it)."""
    from undream.report.data import load_run
    from undream.report.seen import SeenFinder
    from undream.store import open_store

    store = open_store(None, folder / "store")
    finder = SeenFinder(store, work)
    try:
        return store, load_run(store, store.runs()[-1], lambda r, t0: finder(r, t0, folder))
    finally:
        finder.close()


def _perimeter(box, origin: tuple[int, int], factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Sheet pixel coordinates (ys, xs) of the outline of ``box`` (frame pixels) as the sheet draws it."""
    x0, y0 = round(origin[0] + box[0] * factor), round(origin[1] + box[1] * factor)
    x1, y1 = round(origin[0] + box[2] * factor) - 1, round(origin[1] + box[3] * factor) - 1
    xs, ys = np.arange(x0, x1 + 1), np.arange(y0, y1 + 1)
    return (np.concatenate([np.full_like(xs, y0), np.full_like(xs, y1), ys, ys]),
            np.concatenate([xs, xs, np.full_like(ys, x0), np.full_like(ys, x1)]))


def test_results_json_rows_carry_the_detectors_boxes_in_frame_pixels(run):
    from undream.store import open_store
    from undream.victims import load_victim

    results, labels = run["results"], load_victim("bundled:yolo").labels
    store = open_store(None, run["out"] / "store")
    (record,) = store.runs()
    n_boxes, biggest = 0, 0.0
    for side, phase in zip(SIDES, ("pre", "adversarial")):
        stored = [j.result["prediction"] for j in store.jobs(record.id, None, phase)]
        for row, pred in zip(results[side]["per_frame"], stored):
            boxes = row["boxes"]
            assert len(boxes) == min(5, row["n_detections"]) == min(5, len(pred["scores"]))
            scores = [b["score"] for b in boxes]
            assert scores == sorted(scores, reverse=True) and (not boxes or scores[0] == row["score"])
            for b, box, score, label in zip(boxes, pred["boxes"], pred["scores"], pred["labels"]):
                assert b["box"] == pytest.approx(box, abs=0.051) and b["score"] == pytest.approx(score, abs=1e-4)
                assert b["label"] == labels[label]
                x0, y0, x1, y1 = b["box"]
                assert -SIZE / 4 <= x0 < x1 <= SIZE * 1.25 and -SIZE / 4 <= y0 < y1 <= SIZE * 1.25
                biggest = max(biggest, x1, y1)
            x0, y0, x1, y1 = row["truth_box"]
            assert 0 <= x0 < x1 <= SIZE and 0 <= y0 < y1 <= SIZE and x1 - x0 > 4
            n_boxes += len(boxes)
    assert n_boxes > 0, "the detector found nothing: the test would show no box"
    assert biggest > SIZE / 2  # frame pixels (a box may reach past the frame), not fractions of it


def test_the_contact_sheet_draws_each_box_in_its_class_colour(run, tmp_path):
    from undream.report.boxes import OBJECT_RGB, OTHER_RGB
    from undream.report.draw import enlarge
    from undream.report.sheet import contact_sheet

    sheets = _report(run["out"], tmp_path / "rep")
    _, data = _data(run["out"], tmp_path / "work")
    assert data.label == run["results"]["label"] == "sphere" and len(sheets) == len(data.frames)
    drawn = set()
    for frame, sheet in zip(data.frames, sheets):
        _, layout = contact_sheet(data, [frame])
        (row,) = layout.rows
        raw = {"benign": Image.open(run["out"] / "frames_benign" / f"frame_{frame.index:04d}.png"),
               "adversarial": Image.open(run["out"] / "frames_adversarial" / f"frame_{frame.index:04d}.png")}
        for name, side, box in (("benign", frame.benign, row.benign), ("adversarial", frame.adversarial,
                                                                        row.adversarial)):
            x0, y0, x1, y1 = box
            picture = sheet[y0:y1, x0:x1]
            plain = enlarge(np.asarray(raw[name].convert("RGB")), layout.factor)
            assert picture.shape == plain.shape
            assert side.truth is not None and len(side.boxes) == len(run["results"][name]["per_frame"][
                data.frames.index(frame)]["boxes"])
            if not side.boxes:
                continue
            assert not np.array_equal(picture, plain)  # the boxes are drawn on the frame
            best = side.boxes[0]
            colour = OBJECT_RGB if best.label == "sphere" else OTHER_RGB
            ys, xs = _perimeter(best.box, (x0, y0), layout.factor)
            on_edge = np.all(sheet[ys, xs] == colour, axis=1).mean()
            in_frame = np.all(plain.reshape(-1, 3) == colour, axis=1).mean()
            assert on_edge > 0.5 and in_frame < 0.01, (name, frame.index, on_edge, in_frame)
            drawn.add(colour)
            ys, xs = _perimeter(side.truth, (x0, y0), layout.factor)  # dashed black and white
            bw = np.all(sheet[ys, xs] == 0, axis=1) | np.all(sheet[ys, xs] == 255, axis=1)
            assert bw.mean() > 0.3, (name, frame.index, bw.mean())
    assert drawn, "no picture had a box"


def test_a_run_recorded_before_rows_held_boxes_still_makes_a_report(run, tmp_path):
    from undream.report.boxes import UNNAMED_RGB

    old = tmp_path / "old"
    shutil.copytree(run["out"], old)
    store, _ = _data(old, tmp_path / "work0")
    (record,) = store.runs()
    results = json.loads(json.dumps(record.results))
    for side in SIDES:
        for row in results[side]["per_frame"]:
            del row["boxes"], row["truth_box"]
    store.set_results(record.id, results)
    (old / "results.json").write_text(json.dumps(results, indent=1) + "\n")
    sheet = np.concatenate([s.reshape(-1, 3) for s in _report(old, tmp_path / "rep")])
    _, data = _data(old, tmp_path / "work1")
    sides = [s for f in data.frames for s in (f.benign, f.adversarial)]
    assert all(s.truth is None and all(d.label is None for d in s.boxes) for s in sides)
    assert any(s.boxes for s in sides)  # the stored predictions' boxes, drawn without class names
    assert np.all(sheet == UNNAMED_RGB, axis=-1).sum() > 100


def _dashboard(store_dir: Path):
    """A test client of the dashboard over the store of an `undream run` output folder."""
    from undream.dashboard import create_app
    from undream.settings import load_settings

    return create_app(load_settings(env={"UNDREAM_BLOB_URL": str(store_dir), "UNDREAM_CONNECT_TIMEOUT": "1"}))


def _tags(svg: str) -> list[tuple[str, str]]:
    """(fill colour, text) of each ``label score`` tag of an overlay, in the order drawn (best first)."""
    return [(fill, html.unescape(text)) for fill, text in
            re.findall(r'<g class="tag"><rect [^>]*fill="(#[0-9a-f]{6})"/><text [^>]*>([^<]*)</text></g>', svg)]


def test_the_run_page_lays_the_detectors_boxes_over_its_frames(run):
    from undream.report.boxes import OBJECT_RGB, OTHER_RGB

    app = _dashboard(run["out"] / "store")
    client = app.test_client()
    try:
        (run_id,) = [r["id"] for r in client.get("/api/runs").get_json()["runs"]]
        detail = client.get(f"/api/runs/{run_id}").get_json()
        page = client.get(f"/runs/{run_id}").get_data(as_text=True)
        frames = {view: [client.get(u) for u in detail["links"]["frames"][view].values()] for view in SIDES}
    finally:
        app.extensions["undream"].close()
    svgs = re.findall(r'<svg class="boxes".*?</svg>', page, re.S)
    assert len(svgs) == 2 * len(detail["frames"]) == 6 and 'id="boxes-key"' in page and "sphere" in page
    n_tags = 0
    for f, row in enumerate(detail["frames"]):
        for side, svg in zip(SIDES, svgs[2 * f: 2 * f + 2]):
            pred, kept = row[side], run["results"][side]["per_frame"][f]
            # the JSON twin: results.json's boxes, true box and verdict, and the frame's size
            assert pred["detections"] == kept["boxes"] and pred["truth_box"] == kept["truth_box"]
            assert (pred["detected"], pred["truth_label"], pred["size"]) == (kept["detected"], "sphere", [SIZE, SIZE])
            assert svg.count('<g class="truth">') == 1
            tags = _tags(svg)
            assert [t for _, t in tags] == [f"{d['label']} {d['score']:.2f}" for d in kept["boxes"]]
            assert [c for c, _ in tags] == ["#{:02x}{:02x}{:02x}".format(*(OBJECT_RGB if d["label"] == "sphere"
                                                                            else OTHER_RGB)) for d in kept["boxes"]]
            n_tags += len(tags)
    assert n_tags > 0, "the detector found nothing: the test would show no box"
    for view, responses in frames.items():  # the pictures are the frames as rendered: boxes are vectors
        for f, res in enumerate(responses):
            drawn = np.asarray(Image.open(io.BytesIO(res.data)).convert("RGB"))
            raw = np.asarray(Image.open(run["out"] / f"frames_{view}" / f"frame_{f:04d}.png").convert("RGB"))
            assert drawn.shape == (SIZE, SIZE, 3) and np.array_equal(drawn, raw)


def test_a_run_whose_job_rows_hold_no_boxes_still_shows_them(run, tmp_path):
    """Job rows written before they kept the drawn boxes: the page takes them from results.json's rows,
    and without those from the raw predictions (no class names, no true box)."""
    old = tmp_path / "old"
    shutil.copytree(run["out"] / "store", old)
    with sqlite3.connect(old / "undream.db") as db:
        for job_id, text in db.execute("SELECT id, result_json FROM frame_jobs WHERE phase != 'attack'").fetchall():
            result = json.loads(text)
            for key in ("detections", "truth_box", "truth_label", "detected", "size"):
                result["prediction"].pop(key)
            db.execute("UPDATE frame_jobs SET result_json = ? WHERE id = ?", (json.dumps(result), job_id))
    app = _dashboard(old)
    client = app.test_client()
    try:
        (run_id,) = [r["id"] for r in client.get("/api/runs").get_json()["runs"]]
        named = client.get(f"/api/runs/{run_id}").get_json()["frames"]
        store = app.extensions["undream"].store()
        (record,) = store.runs()
        results = json.loads(json.dumps(record.results))
        for side in SIDES:
            for row in results[side]["per_frame"]:
                del row["boxes"], row["truth_box"]
        store.set_results(record.id, results)
        raw = client.get(f"/api/runs/{run_id}").get_json()["frames"]
        page = client.get(f"/runs/{run_id}").get_data(as_text=True)
    finally:
        app.extensions["undream"].close()
    for f, (row, bare) in enumerate(zip(named, raw)):
        for side in SIDES:
            kept = run["results"][side]["per_frame"][f]
            assert row[side]["detections"] == kept["boxes"] and row[side]["truth_box"] == kept["truth_box"]
            assert row[side]["size"] == bare[side]["size"] == [SIZE, SIZE] and bare[side]["truth_box"] is None
            assert [(d["box"], d["score"], d["label"]) for d in bare[side]["detections"]] == \
                [(d["box"], d["score"], None) for d in kept["boxes"]]
    assert '<g class="truth">' not in page and "class not recorded" in page and page.count('<g class="tag">') > 0
