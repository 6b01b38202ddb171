"""``undream evaluate`` (issue 22): a texture judged on scenes, victims and simulators, end to end
through the command; bad inputs are one line each and render nothing."""
from __future__ import annotations

import csv
import json
import os
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from farm_support import LABELS, make_scene, make_victim
from undream.cli import main


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    base = tmp_path_factory.mktemp("evaluate")
    scene = make_scene(base / "scene", n_frames=4, size=24)  # texture 16 × 8 texels
    texture = np.random.default_rng(0).integers(0, 256, (8, 16, 3)).astype(np.uint8)
    np.save(base / "texture.npy", texture.astype(np.float32) / 255.0)
    Image.fromarray(texture).save(base / "texture.png")
    return {"base": base, "scene": scene, "victim": make_victim(base / "victim")}


def _evaluate(*args: str, env: dict[str, str] | None = None):
    return CliRunner().invoke(main, ["evaluate", *args], env={"HF_HUB_OFFLINE": "1", **(env or {})})


def test_a_texture_is_judged_on_every_split_and_written_as_json_and_csv(inputs, tmp_path):
    base = inputs["base"]
    res = _evaluate(str(base / "texture.npy"), str(inputs["scene"]), "--victim", inputs["victim"], "--spp", "2",
                    "--json", str(tmp_path / "rows.json"), "--csv", str(tmp_path / "rows.csv"))
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "rows.json").read_text())["rows"]
    assert [(r["split"], r["frames"]) for r in rows] == [("all", 4), ("attacked", 3), ("held_out", 1)]
    assert all(r["metric"] == "accuracy" and 0 <= r["benign"] <= 1 and 0 <= r["adversarial"] <= 1 for r in rows)
    assert (tmp_path / "rows.csv").read_text().splitlines()[0] == \
        "scene,victim,sim,texture,split,frames,metric,benign,adversarial"
    assert {r["texture"] for r in rows} == {"texture.npy"}
    assert "held_out" in res.output and "→" in res.output
    # the printed table names the victim whole (a folder's path here, longer than any fixed column; a
    # 20-character column once printed bundled:classifier-v3 as "undled:classifier-v3"), columns aligned
    table = [line for line in res.output.splitlines() if "→" in line]
    assert len(table) == 1 + len(rows) and all(str(inputs["victim"]) in line for line in table[1:]), res.output
    assert len({line.index("→") for line in table}) == 1, res.output
    # the same 8-bit texture as a PNG: the same frames, the same verdicts (the evaluation wears 8 bits)
    png = _evaluate(str(base / "texture.png"), str(inputs["scene"]), "--victim", inputs["victim"], "--spp", "2",
                    "--json", str(tmp_path / "png.json"))
    assert png.exit_code == 0, png.output
    assert [{**r, "texture": None} for r in json.loads((tmp_path / "png.json").read_text())["rows"]] == \
        [{**r, "texture": None} for r in rows]


def test_frames_csv_says_which_views_hold(inputs, tmp_path):
    """--frames-csv: one row per frame and victim, with its split and both verdicts, agreeing with the
    table's accuracies; a detector's verdict in its own columns."""
    res = _evaluate(str(inputs["base"] / "texture.npy"), str(inputs["scene"]), "--victim", inputs["victim"],
                    "--victim", "bundled:yolo", "--spp", "2", "--json", str(tmp_path / "rows.json"),
                    "--frames-csv", str(tmp_path / "frames.csv"))
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "rows.json").read_text())["rows"]
    frames = list(csv.DictReader((tmp_path / "frames.csv").open()))
    mine = [f for f in frames if f["victim"] == inputs["victim"]]
    assert [(f["frame"], f["split"]) for f in mine] == [("0", "attacked"), ("1", "attacked"), ("2", "attacked"),
                                                        ("3", "held_out")]
    for prefix, column in (("benign", "benign"), ("texture", "adversarial")):
        assert {f[f"{prefix}_label"] for f in mine} <= set(LABELS)
        right = [f[f"{prefix}_correct"] == "True" for f in mine]
        table = {r["split"]: r[column] for r in rows if r["victim"] == inputs["victim"]}
        assert sum(right) / 4 == pytest.approx(table["all"]) and float(right[3]) == pytest.approx(table["held_out"])
    detector = [f for f in frames if f["victim"] == "bundled:yolo"]
    assert len(detector) == 4 and all(f["texture_detected"] in ("True", "False") and f["texture_label"] == ""
                                      for f in detector)
    assert all(f["truth_box"] == f["benign_top_box"] == "" for f in mine)  # a classifier's rows: no boxes
    # a detector's top box, its class and score, and the object's true box; the JSON holds all its boxes
    frames_json = [f for f in json.loads((tmp_path / "rows.json").read_text())["frames"]
                   if f["victim"] == "bundled:yolo"]
    assert [f["frame"] for f in frames_json] == [int(f["frame"]) for f in detector]
    n_boxes = 0
    for row, full in zip(detector, frames_json):
        x0, y0, x1, y1 = map(float, row["truth_box"].split())
        assert [x0, y0, x1, y1] == full["truth_box"] and 0 <= x0 < x1 <= 24 and 0 <= y0 < y1 <= 24
        for prefix in ("benign", "texture"):
            boxes = full[f"{prefix}_boxes"]
            assert len(boxes) == min(5, full[f"{prefix}_n_detections"]) and f"{prefix}_boxes" not in row
            assert [b["score"] for b in boxes] == sorted((b["score"] for b in boxes), reverse=True)
            if not boxes:
                assert row[f"{prefix}_top_box"] == row[f"{prefix}_top_label"] == "" and full[f"{prefix}_score"] == 0
                continue
            assert [float(v) for v in row[f"{prefix}_top_box"].split()] == boxes[0]["box"] == full[f"{prefix}_top_box"]
            assert row[f"{prefix}_top_label"] == boxes[0]["label"]
            assert float(row[f"{prefix}_score"]) == boxes[0]["score"]
            n_boxes += len(boxes)
    assert n_boxes > 0, "the detector found nothing: the test would check no box"


def test_a_detector_judges_by_ap_against_the_objects_box(inputs, tmp_path):
    """A detector victim is judged by AP@0.5 against the object's box in each frame; ``undream evaluate``
    once built its run without a detection loss, so no frame had a box and every cell read n/a."""
    res = _evaluate(str(inputs["base"] / "texture.npy"), str(inputs["scene"]), "--victim", "bundled:yolo",
                    "--victim", inputs["victim"], "--spp", "2", "--json", str(tmp_path / "rows.json"))
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "rows.json").read_text())["rows"]
    detector = [r for r in rows if r["victim"] == "bundled:yolo"]
    assert [r["split"] for r in detector] == ["all", "attacked", "held_out"]
    assert all(r["metric"] == "ap50" and 0 <= r["benign"] <= 1 and 0 <= r["adversarial"] <= 1 for r in detector)
    assert "n/a" not in res.output


@pytest.mark.parametrize("texture, extra, needle", [
    ("wrong", [], "TEXTURE wrong.npy: 8×4 texels, but scene"),
    ("texture.npy", ["--victim", "bundled:no-such-victim"], "no-such-victim"),
    ("missing.npy", [], "TEXTURE"),
    ("texture.npy", ["--json", "/no/such/folder/rows.json"], "--json /no/such/folder/rows.json: its folder"),
    ("texture.npy", ["--sim", "povray"], "sim"),
])
def test_bad_inputs_are_one_line(inputs, texture, extra, needle):
    base = inputs["base"]
    if texture == "wrong":
        np.save(base / "wrong.npy", np.zeros((4, 8, 3), np.float32))  # another object's layout
        texture = "wrong.npy"
    extra = [inputs["victim"] if e == "VICTIM" else e for e in extra]
    args = [str(base / texture), str(inputs["scene"]), *extra]
    if "--victim" not in extra:
        args += ["--victim", inputs["victim"]]
    res = _evaluate(*args, "--spp", "1")
    assert res.exit_code != 0
    lines = [line for line in res.output.strip().splitlines() if line]
    assert len(lines) == 1 and needle in lines[0], res.output


def test_holdout_takes_the_mapping_its_message_offers(inputs, tmp_path):
    """Issue 41: `--holdout '{every: 2}'` was refused by a message offering `{every: N, offset: K}`
    (the option's text was never parsed). Now the YAML mapping is the run config's holdout; text
    that is none of the forms is one line saying which are."""
    args = [str(inputs["base"] / "texture.npy"), str(inputs["scene"]), "--victim", inputs["victim"], "--spp", "1"]
    for holdout, held in (("{every: 2}", 2), ("every: 2", 2), ("{every: 2, offset: 1}", 2), ("{frames: [0]}", 1), ("none", 0)):
        res = _evaluate(*args, "--holdout", holdout, "--json", str(tmp_path / "rows.json"))
        assert res.exit_code == 0, (holdout, res.output)
        rows = json.loads((tmp_path / "rows.json").read_text())["rows"]
        assert [r["frames"] for r in rows if r["split"] == "held_out"] in ([held], []), (holdout, rows)
    for holdout, needle in (("evry", "'evry' is neither auto, none nor a YAML mapping"),
                            ("[1, 2]", "neither auto, none nor a YAML mapping"),
                            ("{every: 1}", "holdout.every"), ("{evry: 2}", "got {'evry': 2}")):
        res = _evaluate(*args, "--holdout", holdout)
        lines = [line for line in res.output.strip().splitlines() if line]
        assert res.exit_code == 2 and len(lines) == 1 and needle in lines[0], (holdout, res.output)


@pytest.mark.parametrize("case", ["texture", "scene file", "in the scene", "same file", "folder",
                                  "another run's results"])
def test_an_output_file_never_replaces_an_input_or_a_result(inputs, tmp_path, case):
    """--json/--csv/--frames-csv are checked before any render: a swapped argument that names the
    texture, a file of a scene directory or of a run's output folder, one file twice or a folder
    is refused in one line, and every file is left as it was."""
    base, scene = inputs["base"], inputs["scene"]
    texture = base / "texture.npy"
    run = tmp_path / "run"
    run.mkdir()
    (run / "metadata.json").write_text(json.dumps({"undream_output": "run"}))
    (run / "results.json").write_text("{}\n")
    args, needle, kept = {
        "texture": (["--json", str(texture)], f"--json {texture}: is this command's input", texture),
        "scene file": (["--csv", str(scene / "sequence.json")], "this command's input", scene / "sequence.json"),
        "in the scene": (["--frames-csv", str(scene / "metadata.json")], "this command's input",
                         scene / "metadata.json"),
        "same file": (["--json", str(tmp_path / "rows"), "--csv", str(tmp_path / "rows")],
                      "--json names the same file", None),
        "folder": (["--csv", str(tmp_path)], "is a folder; give a file name", None),
        "another run's results": (["--json", str(run / "results.json")],
                                  f"would replace a file of the output folder of `undream run` {run}",
                                  run / "results.json"),
    }[case]
    before = None if kept is None else kept.read_bytes()
    res = _evaluate(str(texture), str(scene), "--victim", inputs["victim"], "--spp", "1", *args)
    lines = [line for line in res.output.strip().splitlines() if line]
    assert res.exit_code != 0 and len(lines) == 1 and needle in lines[0], res.output
    if kept is not None:
        assert kept.read_bytes() == before
    assert not (tmp_path / "rows").exists()


@pytest.mark.parametrize("case", ["victim folder", "settings", "settings variable", "fifo", "device", "symlink",
                                  "victim of the run"])
def test_an_output_file_never_replaces_a_victim_file_the_settings_or_a_special_file(inputs, tmp_path, case):
    """Issue 41: ``--json myvictim/config.json --victim ./myvictim`` overwrote the victim's config,
    ``--json``/``--csv`` naming the ``--settings`` file overwrote it, and a FIFO or a device was
    replaced by a regular file. Each is refused in one line before any render and left as it was."""

    base, scene = inputs["base"], inputs["scene"]
    victim = tmp_path / "myvictim"
    shutil.copytree(inputs["victim"], victim)
    settings = tmp_path / "settings.yaml"
    settings.write_text(f"blob_url: {tmp_path / 'blobs'}\n")
    texture, extra, env = str(base / "texture.npy"), ["--victim", str(victim)], {}
    if case == "victim folder":
        target, needle = victim / "config.json", f"lies in {victim}, this command's input"
    elif case in ("settings", "settings variable"):
        target, needle = settings, "is this command's input"
        extra += ["--settings", str(settings)] if case == "settings" else []
        env = {} if case == "settings" else {"UNDREAM_SETTINGS": str(settings)}
    elif case == "fifo":
        target, needle = tmp_path / "rows.fifo", "is a FIFO (named pipe), not a regular file"
        os.mkfifo(target)
    elif case == "device":  # a node of its own (never /dev/null: a regression run as root would replace it)
        target, needle = tmp_path / "null", "is a character device, not a regular file"
        try:
            os.mknod(target, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        except PermissionError:
            pytest.skip("no permission to make a device node (mknod) here")
    elif case == "symlink":
        target, needle = tmp_path / "latest.json", "is a symbolic link, not a regular file"
        (tmp_path / "rows.json").write_text("an earlier evaluation\n")
        target.symlink_to(tmp_path / "rows.json")
    else:  # TEXTURE is a run folder whose config names ./myvictim: judged by it, so it is an input
        run = tmp_path / "run"
        run.mkdir()
        np.save(run / "texture_final.npy", np.load(base / "texture.npy"))
        (run / "metadata.json").write_text(json.dumps({"undream_output": "run", "config": {"victim": str(victim)}}))
        texture, extra, target = str(run), [], victim / "preprocessor_config.json"
        needle = f"lies in {victim}, this command's input"
    kind = os.lstat(target).st_mode
    before = None if case in ("fifo", "device") else target.read_bytes()
    option = "--csv" if case == "settings variable" else "--json"
    res = _evaluate(texture, str(scene), *extra, "--spp", "1", option, str(target), env=env)
    lines = [line for line in res.output.strip().splitlines() if line and not line.startswith("victim:")]
    assert res.exit_code == 2 and len(lines) == 1 and f"{option} {target}: " in lines[0], res.output
    assert needle in lines[0], res.output
    assert os.lstat(target).st_mode == kind and (before is None or target.read_bytes() == before)
    assert "→" not in res.output  # no table: nothing was rendered


def test_an_output_file_may_be_new_in_a_run_folder_or_replace_a_file_of_ones_own(inputs, tmp_path):
    """What the rule leaves alone: a new file in another run's folder, and a file written before
    (evaluating again replaces it, whole)."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "metadata.json").write_text(json.dumps({"undream_output": "run"}))
    again = tmp_path / "rows.csv"
    again.write_text("an earlier evaluation\n")
    res = _evaluate(str(inputs["base"] / "texture.npy"), str(inputs["scene"]), "--victim", inputs["victim"],
                    "--spp", "1", "--json", str(run / "transfer.json"), "--csv", str(again))
    assert res.exit_code == 0, res.output
    assert json.loads((run / "transfer.json").read_text())["rows"]
    assert "split" in again.read_text().splitlines()[0].split(",")
    assert not list(tmp_path.glob(".*.tmp")) and not list(run.glob(".*.tmp"))


def test_a_runs_texture_on_a_scene_with_another_uv_layout_is_one_line(inputs, tmp_path):
    """An `undream run` output folder names its scene: a scene whose object has other UVs is refused."""
    import dataclasses
    import json as json_

    from undream.scene.mesh import read_ply, write_ply

    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "texture_final.npy", np.load(inputs["base"] / "texture.npy"))
    (run / "metadata.json").write_text(json_.dumps({"scene_dir": str(inputs["scene"])}))
    other = tmp_path / "other"
    shutil.copytree(inputs["scene"], other)
    mesh = read_ply(other / "meshes" / "object.ply")
    write_ply(dataclasses.replace(mesh, uvs=mesh.uvs[:, ::-1].copy()), other / "meshes" / "object.ply")
    res = _evaluate(str(run), str(other), "--victim", inputs["victim"], "--spp", "1")
    lines = [line for line in res.output.strip().splitlines() if line]
    assert res.exit_code != 0 and len(lines) == 1, res.output
    assert f"SCENE {other}: its object has another UV layout than the scene the texture was optimised on" in lines[0]
    same = _evaluate(str(run), str(inputs["scene"]), "--victim", inputs["victim"], "--spp", "1")
    assert same.exit_code == 0, same.output  # its own scene: the same layout


def test_a_runs_texture_on_a_scene_with_another_uv_scale_is_one_line_naming_both(inputs, tmp_path):
    """Issue 41: the same mesh and resolution with the texture repeated twice (uv_scale 2) was judged
    without a word, every texel landing elsewhere (a conditions run refuses such a scene)."""
    import dataclasses

    from undream.spec.io import load_sequence, save_sequence

    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "texture_final.npy", np.load(inputs["base"] / "texture.npy"))
    (run / "metadata.json").write_text(json.dumps({"scene_dir": str(inputs["scene"])}))
    other = tmp_path / "tiled"
    shutil.copytree(inputs["scene"], other)
    seq = load_sequence(other / "sequence.json")
    save_sequence(dataclasses.replace(seq, asset=dataclasses.replace(
        seq.asset, texture=dataclasses.replace(seq.texture, uv_scale=(2.0, 2.0)))), other / "sequence.json")
    res = _evaluate(str(run), str(other), "--victim", inputs["victim"], "--spp", "1", "--json", str(tmp_path / "r.json"))
    lines = [line for line in res.output.strip().splitlines() if line]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert lines[0] == (f"undream: error: SCENE {other}: its texture is 16×8 texels at uv_scale 2×2, the scene the "
                        f"texture was optimised on ({inputs['scene']}) has 16×8 texels at uv_scale 1×1: its texels "
                        "would land elsewhere"), lines[0]
    assert not (tmp_path / "r.json").exists()


def test_a_runs_texture_is_judged_by_the_victim_it_was_attacked_against(inputs, tmp_path):
    """Without --victim, an `undream run` folder's texture is judged by its run config's victim (the
    main job attacks bundled:classifier-v3; judging it by the default bundled:classifier measured
    another victim without saying so), and the command says which; --victim still chooses."""
    run = tmp_path / "run"
    run.mkdir()
    np.save(run / "texture_final.npy", np.load(inputs["base"] / "texture.npy"))
    (run / "metadata.json").write_text(json.dumps({"scene_dir": str(inputs["scene"]),
                                                   "config": {"victim": inputs["victim"]}}))
    res = _evaluate(str(run), str(inputs["scene"]), "--spp", "1", "--json", str(tmp_path / "rows.json"))
    assert res.exit_code == 0, res.output
    assert {r["victim"] for r in json.loads((tmp_path / "rows.json").read_text())["rows"]} == {inputs["victim"]}
    assert f"victim: {inputs['victim']} (the one TEXTURE was attacked against; --victim to choose)" in res.output
    other = make_victim(tmp_path / "other_victim")
    chosen = _evaluate(str(run), str(inputs["scene"]), "--spp", "1", "--victim", other,
                       "--json", str(tmp_path / "chosen.json"))
    assert chosen.exit_code == 0, chosen.output
    assert {r["victim"] for r in json.loads((tmp_path / "chosen.json").read_text())["rows"]} == {other}
    assert "victim:" not in chosen.output


def test_a_farm_sweeps_final_textures_are_judged_by_name(inputs, tmp_path):
    """TEXTURE as a sweep of the farm (by name) or one of its runs (by id): every final texture."""
    from scheduler.scenes import store_scene
    from undream.store import NewRun, open_store

    texture = np.load(inputs["base"] / "texture.npy")
    blobs = tmp_path / "farm"
    with open_store(None, blobs) as store:
        scene_ref = store_scene(store.blobs, inputs["scene"])
        runs = [NewRun(f"eps{e}", {"scene": "s", "name": f"eps{e}"}, 4, 0, scene_ref=scene_ref) for e in (8, 16)]
        store.create_sweep("eps-grid", {"grid": {"attack.eps": [8, 16]}}, runs)
        store.put_final_texture(runs[0].id, texture)
        store.put_final_texture(runs[1].id, 1 - texture)
    farm = {"UNDREAM_CACHE_DIR": str(tmp_path / "cache")}  # where the runs' scene is unpacked
    env = ["--blobs", str(blobs), "--victim", inputs["victim"], "--spp", "1"]
    res = _evaluate("eps-grid", str(inputs["scene"]), *env, "--json", str(tmp_path / "sweep.json"), env=farm)
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "sweep.json").read_text())["rows"]
    assert [r["texture"] for r in rows if r["split"] == "all"] == [f"eps8 ({runs[0].id[:8]})", f"eps16 ({runs[1].id[:8]})"]
    assert (tmp_path / "cache" / "scenes").is_dir()
    one = _evaluate(runs[0].id[:8], str(inputs["scene"]), *env, "--json", str(tmp_path / "run.json"), env=farm)
    assert one.exit_code == 0, one.output
    assert [r for r in json.loads((tmp_path / "run.json").read_text())["rows"]] == rows[:3]
    nothing = _evaluate("no-such-sweep", str(inputs["scene"]), *env, env=farm)
    assert nothing.exit_code != 0 and "TEXTURE no-such-sweep: no such file, and no run or sweep" in nothing.output
    # without --victim: the victim the farm's runs attacked (their configs'), named on stderr
    with open_store(None, blobs) as store:
        attacked = [NewRun("v", {"scene": "s", "name": "v", "victim": inputs["victim"]}, 4, 0, scene_ref=scene_ref)]
        store.create_sweep("with-victim", {}, attacked)
        store.put_final_texture(attacked[0].id, texture)
    own = _evaluate("with-victim", str(inputs["scene"]), "--blobs", str(blobs), "--spp", "1",
                    "--json", str(tmp_path / "own.json"), env=farm)
    assert own.exit_code == 0, own.output
    assert {r["victim"] for r in json.loads((tmp_path / "own.json").read_text())["rows"]} == {inputs["victim"]}
    assert f"victim: {inputs['victim']} (the one TEXTURE was attacked against" in own.output
    # with --victim the runs' configs are not read: a run stored by another version (a config this one
    # cannot type) is still judged
    with open_store(None, blobs) as store:
        odd = [NewRun("odd", {"scene": "s", "name": "odd", "attack": {"epsilon": 8}}, 4, 0, scene_ref=scene_ref)]
        store.create_sweep("odd-config", {}, odd)
        store.put_final_texture(odd[0].id, texture)
    judged = _evaluate("odd-config", str(inputs["scene"]), *env, env=farm)
    assert judged.exit_code == 0 and "odd (" in judged.output, judged.output


@pytest.mark.slow
def test_the_same_texture_judged_in_blender(inputs, cycles, tmp_path):
    res = _evaluate(str(inputs["base"] / "texture.npy"), str(inputs["scene"]), "--victim", inputs["victim"],
                    "--sim", "blender", "--spp", "2", "--json", str(tmp_path / "rows.json"))
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "rows.json").read_text())["rows"]
    assert [(r["sim"], r["split"], r["frames"]) for r in rows] == \
        [("blender", "all", 4), ("blender", "attacked", 3), ("blender", "held_out", 1)]
    assert all(0 <= r["adversarial"] <= 1 for r in rows)


def test_the_held_out_conditions_wear_the_main_jobs_texture():
    """examples/conditions/ (scripts/condition_suite.py): each loads, and its object and texture are the
    main job's scene's, so the main job's texture fits every one; each differs from it in its scene."""
    from undream.scene.sources import sequence_from_file as load_sequence

    root = Path(__file__).resolve().parents[1] / "examples"
    main_job = load_sequence(root / "bin_orbit.yaml")
    specs = sorted((root / "conditions").glob("*.yaml"))
    assert len(specs) == 8
    for path in specs:
        seq = load_sequence(path)
        assert seq.asset == main_job.asset and len(seq.frames) == len(main_job.frames), path.name
        assert seq.frames != main_job.frames, path.name
