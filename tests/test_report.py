"""``undream report``: a real tiny run and a real tiny sweep (4 frames of 16 px, one attack step), reported.

The sweep runs through the farm's stages in this process (validated, recorded
with a sweep id, drained like `undream run` does); the run is an `undream run`
output folder with frames 1 and 3 held out.
"""
from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from farm_support import make_scene, make_victim, run_config, write_yaml

HELD = [1, 3]  # positions (= indices) held out in the `undream run` run


@pytest.fixture(scope="module")
def farm(tmp_path_factory) -> dict:
    from scheduler.contexts import ContextCache
    from scheduler.local import LocalDispatch, drain, run_local
    from scheduler.submit import Validator, record
    from scheduler.sweep import load_sweep
    from undream.settings import load_settings
    from undream.spec.run import RunConfig
    from undream.store import open_store

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    root = tmp_path_factory.mktemp("report")
    victim = make_victim(root / "victim")
    scene = make_scene(root / "scene", n_frames=4, size=16)
    base = run_config(scene, victim, name="base", steps=1, label="umbrella")
    write_yaml(root / "sweep.yaml", {"name": "tiny", "base": base,
                                     "grid": {"attack.eps": [8, 64], "seed": [0, 1]}})
    sweep = load_sweep(root / "sweep.yaml")
    database, blobs = f"sqlite:///{root}/farm.db", root / "blobs"
    settings = load_settings(env={"UNDREAM_DATABASE_URL": database, "UNDREAM_BLOB_URL": str(blobs)})
    store = open_store(settings.database_url, settings.blob_url)
    prepared = [Validator(root / "work")(r.config, r.base_dir) for r in sweep.runs]
    sweep_id = store.create_sweep(sweep.name, sweep.spec)
    dispatch = LocalDispatch()
    for run_id in record(store, prepared, settings, root / "outs", sweep_id=sweep_id, out_per_run=True):
        dispatch.start(run_id)
    drain(store, ContextCache(store, root / "cache"), dispatch)
    one = RunConfig.from_json({**base, "name": "one", "holdout": {"frames": HELD}})
    run_local(one, root / "run", base_dir=root, progress=False)
    return {"root": root, "store": store, "sweep_id": sweep_id, "run": root / "run",
            "db": ["--database", database, "--blobs", str(blobs)]}


def _cli(*args: str):
    from undream.cli import main

    return CliRunner().invoke(main, ["report", *args])


def _local_data(farm: dict):
    from scheduler.preflight import is_run_output
    from undream.report.data import load_run
    from undream.report.seen import SeenFinder
    from undream.store import open_store

    assert is_run_output(farm["run"])
    store = open_store(None, farm["run"] / "store")
    run = store.runs()[-1]
    finder = SeenFinder(store, farm["root"] / "seen-work")
    try:
        return load_run(store, run, lambda r, t0: finder(r, t0, farm["run"]))
    finally:
        finder.close()


def test_run_report_from_an_output_folder(farm, tmp_path):
    out = tmp_path / "rep"
    res = _cli(str(farm["run"]), "--out", str(out))
    assert res.exit_code == 0, res.output
    html = (out / "index.html").read_text()
    for name in ("loss.png", "texture.png", "headline.csv", "frames.csv"):
        assert (out / name).is_file() and f'"{name}"' in html
    for i in range(4):  # the grid: a thumbnail per frame and side, each a link to the frame's full picture
        for name in (f"frames/frame_{i:04d}.png", f"thumbs/adversarial/frame_{i:04d}.png",
                     f"thumbs/benign/frame_{i:04d}.png"):
            assert (out / name).is_file() and f'"{name}"' in html, name
    headline_html = html[html.index("<table id=headline>"):]
    headline_html = headline_html[:headline_html.index("</table>")]
    assert "0 2" not in headline_html and "1 3" not in headline_html  # counts in the table, lists in the CSV
    assert "<td class=n>2</td>" in headline_html and "<td class=n>4</td>" in headline_html
    assert "<script" not in html and 'src="http' not in html and 'href="http' not in html
    assert f"undream report {farm['run']} --out {out}" in html
    headline = list(csv.DictReader(io.StringIO((out / "headline.csv").read_text())))
    assert [r["split"] for r in headline] == ["attacked frames", "held-out frames", "all frames"]
    assert headline[1]["frames"] == "1 3" and headline[0]["frames"] == "0 2"
    frames = list(csv.DictReader(io.StringIO((out / "frames.csv").read_text())))
    assert [r["split"] for r in frames] == ["attacked", "held-out", "attacked", "held-out"]
    assert json.loads((out / "report.json").read_text())["kind"] == "run"


def test_contact_sheet_has_a_row_per_frame_with_held_out_ones_marked(farm, tmp_path):
    from PIL import Image

    from undream.report.sheet import ATTACKED_RGB, HELD_OUT_RGB, contact_sheet

    data = _local_data(farm)
    sheet, layout = contact_sheet(data)
    assert [r.index for r in layout.rows] == [0, 1, 2, 3]
    assert [r.held_out for r in layout.rows] == [i in HELD for i in range(4)]
    pixels = np.asarray(sheet)
    for row, frame in zip(layout.rows, data.frames):
        x0, y0, x1, y1 = row.band
        assert tuple(pixels[y1 - 3, (x0 + x1) // 2]) == (HELD_OUT_RGB if row.held_out else ATTACKED_RGB)
        for box, side in ((row.benign, frame.benign), (row.adversarial, frame.adversarial)):
            bx0, by0, bx1, by1 = box
            assert (bx1 - bx0, by1 - by0) == (16 * layout.factor, 16 * layout.factor)
            assert np.array_equal(pixels[by0:by1:layout.factor, bx0:bx1:layout.factor], side.image)
            colour = HELD_OUT_RGB if row.held_out else ATTACKED_RGB
            assert tuple(pixels[by0 - 1, bx0 + 5]) == colour  # the picture's frame, in its split's colour
    out = tmp_path / "rep"
    assert _cli(str(farm["run"]), "--out", str(out)).exit_code == 0
    for frame in data.frames:  # each frame's full picture is its row of the sheet
        written = np.asarray(Image.open(out / f"frames/frame_{frame.index:04d}.png").convert("RGB"))
        one, one_layout = contact_sheet(data, [frame])
        (row,) = one_layout.rows
        assert np.array_equal(written, np.asarray(one)) and row.held_out == (frame.index in HELD)
        thumb = np.asarray(Image.open(out / f"thumbs/adversarial/frame_{frame.index:04d}.png").convert("RGB"))
        assert np.array_equal(thumb, frame.adversarial.image)  # 16 px frames: thumbnails as they are


def test_unseen_texels_come_from_the_scenes_visibility(farm):
    data = _local_data(farm)
    mask = data.seen.mask
    assert mask is not None and mask.shape == data.texture0.shape[:2]
    assert 0 < int(mask.sum()) < mask.size  # a sphere's texture: the cameras miss some of it
    changed = np.any(data.texture_final != data.texture0, axis=2)
    assert changed.any() and not (changed & ~mask).any()  # the attack changed only texels some frame sees
    assert "every frame, attacked and held-out" in data.seen.how


def test_sweep_report(farm, tmp_path):
    out = tmp_path / "sweep"
    res = _cli("tiny", "--out", str(out), *farm["db"])
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader(io.StringIO((out / "results.csv").read_text())))
    assert [(r["attack.eps"], r["seed"]) for r in rows] == [("8", "0"), ("8", "1"), ("64", "0"), ("64", "1")]
    assert all(r["status"] == "done" and r["held_out_adversarial"] != "" for r in rows)
    cells = list(csv.DictReader(io.StringIO((out / "comparison.csv").read_text())))
    assert {(c["metric"], c["x"], c["n_seeds"]) for c in cells if c["metric"] != "success"} == {
        (s, e, "2") for s in ("attacked", "held_out") for e in ("8", "64")}
    html = (out / "index.html").read_text()
    for i in range(4):
        assert f'href="runs/tiny-00{i}/index.html"' in html and (out / f"runs/tiny-00{i}/frames/frame_0000.png").is_file()
    assert "compare_held_out.png" in html and "All 4 runs finished" in html
    assert '<a href="../../index.html">' in (out / "runs/tiny-000/index.html").read_text()


def test_cells_average_over_seeds():
    from undream.report.compare import Cell

    c = Cell("pgd", 8, "held_out", (0.25, 0.75), 2)
    assert c.mean == pytest.approx(0.5) and c.std == pytest.approx(0.3535534, rel=1e-6)
    assert Cell("pgd", 8, "attacked", (0.5,), 3).std is None and Cell("pgd", 8, "attacked", (), 3).mean is None


def _nothing_written(parent: Path, out: Path) -> None:
    assert not out.exists()
    assert [p.name for p in parent.iterdir() if p.name.startswith(f".{out.name}")] == []


@pytest.mark.parametrize("target, words", [
    ("no-such-sweep", "TARGET 'no-such-sweep': no such folder"),
    ("{scene}", "not an output folder of `undream run`"),
    ("{sweep_yaml}", "not an output folder of `undream run`, a run id or a sweep"),
    ("{farm_output}", "give its run id"),  # a submitted run's outputs: no store/ in them
])
def test_bad_targets_are_one_line_and_write_nothing(farm, tmp_path, target, words):
    target = target.format(scene=farm["root"] / "scene", sweep_yaml=farm["root"] / "sweep.yaml",
                           farm_output=farm["root"] / "outs" / "tiny-000")
    res = _cli(target, "--out", str(tmp_path / "rep"), *farm["db"])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1 and words in res.stderr, res.stderr
    _nothing_written(tmp_path, tmp_path / "rep")


def test_an_unfinished_run_is_refused(farm, tmp_path):
    run_id = farm["store"].create_run("queued-one", {"attack": {"name": "pgd", "eps": 8}}, 4, 0)
    res = _cli(run_id, "--out", str(tmp_path / "rep"), *farm["db"])
    assert res.exit_code == 2 and "is queued; a report needs a finished run" in res.stderr, res.stderr
    _nothing_written(tmp_path, tmp_path / "rep")
    farm["store"].delete_run(run_id)


def test_out_refuses_anything_but_a_report(farm, tmp_path):
    before = sorted(p.name for p in farm["run"].iterdir())
    res = _cli(str(farm["run"]), "--out", str(farm["run"]), "--force")
    assert res.exit_code == 2 and "is not a report" in res.stderr
    assert sorted(p.name for p in farm["run"].iterdir()) == before
    out = tmp_path / "rep"
    assert _cli(str(farm["run"]), "--out", str(out)).exit_code == 0
    res = _cli(str(farm["run"]), "--out", str(out))
    assert res.exit_code == 2 and "give --force" in res.stderr
    (out / "stale.txt").write_text("from the old report")
    assert _cli(str(farm["run"]), "--out", str(out), "--force").exit_code == 0
    assert not (out / "stale.txt").exists() and (out / "index.html").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["rep"]


def test_a_store_target_on_the_default_sqlite_database(tmp_path):
    """Without --database the farm's store is SQLite in the blob folder (the report crashed on it)."""
    from undream.store import open_store

    open_store(None, tmp_path / "blobs").close()
    res = CliRunner().invoke(__import__("undream.cli", fromlist=["main"]).main,
                             ["report", "nosuch", "--out", str(tmp_path / "rep"), "--blobs", str(tmp_path / "blobs")],
                             env={"UNDREAM_DATABASE_URL": ""})
    assert res.exit_code == 2, res.output
    assert "the SQLite store in" in res.stderr and not (tmp_path / "rep").exists()


def test_a_finished_sweep_read_with_another_blob_folder_says_where_it_looked(farm, tmp_path):
    """The farm's database with the wrong --blobs used to say only 'no final texture in the store'."""
    database = farm["db"][1]
    elsewhere = tmp_path / "other_blobs"
    res = _cli("tiny", "--out", str(tmp_path / "rep"), "--database", database, "--blobs", str(elsewhere))
    assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.stderr
    assert f"no final texture under {elsewhere}" in res.stderr and "UNDREAM_BLOB_URL / --blobs" in res.stderr
    _nothing_written(tmp_path, tmp_path / "rep")


def test_a_run_report_shows_what_undream_evaluate_measured_beside_its_own_numbers(farm, tmp_path):
    from undream.cli import main

    files = []
    for holdout in ("auto", "none"):  # the run's texture judged again on its scene, two ways
        files.append(tmp_path / f"ev_{holdout}.json")
        res = CliRunner().invoke(main, ["evaluate", str(farm["run"]), str(farm["root"] / "scene"), "--spp", "2",
                                        "--holdout", holdout, "--json", str(files[-1])])
        assert res.exit_code == 0, res.output
    out = tmp_path / "rep"
    res = _cli(str(farm["run"]), "--out", str(out), *[p for f in files for p in ("--evaluation", str(f))])
    assert res.exit_code == 0, res.output
    html = (out / "index.html").read_text()
    table = html[html.index("<table id=transfer"):]
    table, legend = table[:table.index("</table>")], table[table.index("</table>"):table.index("</p>")]
    assert f"[1] <code>{files[0]}</code>: texture" in legend and f"[2] <code>{files[1]}</code>" in legend
    rows = list(csv.DictReader(io.StringIO((out / "transfer.csv").read_text())))
    assert [r["source"] for r in rows] == ["this run (results.json)", str(files[0]), str(files[1])]
    results = json.loads((farm["run"] / "results.json").read_text())
    assert float(rows[0]["held_out_adversarial"]) == results["held_out"]["adversarial"]["value"]
    assert rows[0]["held_out_frames"] == "2" and rows[0]["all_frames"] == "4"
    for row, path in zip(rows[1:], files):
        judged = {r["split"]: r for r in json.loads(path.read_text())["rows"]}
        assert float(row["all_adversarial"]) == pytest.approx(judged["all"]["adversarial"])
        assert float(row["all_benign"]) == pytest.approx(judged["all"]["benign"])
        assert row["attacked_frames"] == str(judged["attacked"]["frames"])
    assert rows[1]["held_out_frames"] == "1" and rows[2]["held_out_frames"] == ""  # auto: every 4th of 4; none
    assert table.count("<tr>") == 4 and "<td>this run</td>" in table and "<td>[2]</td>" in table
    assert f"--evaluation {files[0]} --evaluation {files[1]}" in html  # the command under the charts


@pytest.mark.parametrize("content, words", [
    ("not json", "not JSON"),
    ('{"texture": "t.npy"}', "no list of rows"),
    ('{"rows": [{"scene": "s"}]}', "rows[0] lacks victim, split, frames, metric, benign, adversarial"),
])
def test_a_bad_evaluation_file_is_one_line_and_writes_nothing(farm, tmp_path, content, words):
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    res = _cli(str(farm["run"]), "--out", str(tmp_path / "rep"), "--evaluation", str(bad))
    assert res.exit_code == 2 and res.stderr.count("\n") == 1 and f"--evaluation {bad}: " in res.stderr, res.stderr
    assert words in res.stderr, res.stderr
    _nothing_written(tmp_path, tmp_path / "rep")


def test_evaluations_go_beside_a_run_not_a_sweep(farm, tmp_path):
    ev = tmp_path / "ev.json"
    ev.write_text('{"texture": "t.npy", "rows": []}')
    res = _cli("tiny", "--out", str(tmp_path / "rep"), "--evaluation", str(ev), *farm["db"])
    assert res.exit_code == 2 and "is a sweep" in res.stderr, res.stderr
    _nothing_written(tmp_path, tmp_path / "rep")
