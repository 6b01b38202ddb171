"""Multi-condition runs: one texture attacked over several scenes of one object (issue #22).

Through ``undream run`` and ``undream submit`` (a real worker on a real broker): the frames of
every condition are the attack's, whole conditions held out are never attacked and are judged
apart, each condition's frames are the ones its scene has alone, and a farm run ends on the
local run's texture. Bad conditions are refused in one line, before anything is written.
"""
from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from conftest import service_missing
from farm_support import Farm, make_scene, make_victim, redis_up, run_config, write_yaml

ROOT = Path(__file__).resolve().parents[1]

SPEC = {  # a small park scene: its background props depend on the scene's cameras and seed
    "name": "ball", "seed": 3, "frames": 4, "fps": 4,
    "camera": {"fov": 40, "resolution": [16, 16],
               "path": {"type": "orbit", "center": [0, 0, 0], "radius": 2.6, "height": 1.0,
                        "start_deg": 0, "end_deg": 90},
               "look_at": "object", "look_at_offset": [0, 0.4, 0]},
    "object": {"asset": {"name": "ball", "mesh": "builtin:sphere",
                         "texture": {"resolution": [16, 8], "init": [0.5, 0.5, 0.5]}},
               "path": {"type": "static", "position": [0, 0, 0]}},
    "environment": {"weather": "clear", "time_of_day": 14.0, "background": "park"},
}
GRID = {"camera.path.height": [0.6, 1.4], "environment.weather": ["clear", "fog"]}  # in the order YAML keeps
NAMES = ["height_0p6-weather_clear", "height_0p6-weather_fog", "height_1p4-weather_clear", "height_1p4-weather_fog"]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, mi):
    root = tmp_path_factory.mktemp("conditions")
    spec = write_yaml(root / "ball.yaml", SPEC)
    return {"root": root, "spec": spec, "victim": make_victim(root / "victim")}


def _config(inputs, name: str, **extra) -> dict:
    cfg = run_config(inputs["spec"], inputs["victim"], name=name, steps=3, **extra)
    cfg.setdefault("conditions", {"grid": GRID, "holdout": [NAMES[3]]})
    return cfg


def _undream(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "undream.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


@pytest.fixture(scope="module")
def local_run(inputs):
    """The grid run through `undream run` (4 conditions × 4 frames, one held out)."""
    out = inputs["root"] / "out"
    res = _undream("run", write_yaml(inputs["root"] / "grid.yaml", _config(inputs, "grid")), "--out", out,
                   "--no-progress")
    assert res.returncode == 0, res.stderr
    return {"out": out, "stdout": res.stdout, "results": json.loads((out / "results.json").read_text())}


def test_a_grid_run_attacks_every_condition_but_the_held_out_one(local_run):
    from undream.spec import load_sequence
    from undream.store import open_store

    seq = load_sequence(local_run["out"] / "scene" / "sequence.json")
    assert [c.name for c in seq.conditions] == NAMES and len(seq.frames) == 16
    res = local_run["results"]
    # holdout auto within each condition (its 4th frame), the last condition whole
    assert res["attacked"]["frames"] == [0, 1, 2, 4, 5, 6, 8, 9, 10]
    assert res["held_out"]["frames"] == [3, 7, 11]
    assert res["held_out_conditions"]["frames"] == [12, 13, 14, 15]
    rows = {row["name"]: row for row in res["conditions"]}
    assert list(rows) == NAMES and [r["held_out"] for r in rows.values()] == [False, False, False, True]
    assert rows[NAMES[2]]["frames"] == [8, 9, 10, 11]
    per_frame = {r["frame"]: r for r in res["adversarial"]["per_frame"]}
    accuracy = np.mean([per_frame[f]["correct"] for f in (12, 13, 14, 15)])
    assert res["held_out_conditions"]["adversarial"]["value"] == pytest.approx(accuracy)
    with open_store(None, local_run["out"] / "store") as store:
        (run,) = store.runs()
        attacked = {j.frame for j in store.jobs(run.id, None, "attack")}
        judged = {j.frame for j in store.jobs(run.id, run.iteration, "adversarial")}
    assert attacked == {0, 1, 2, 4, 5, 6, 8, 9, 10}  # never a held-out view or condition
    assert judged == set(range(16))
    assert run.farm["attacked"] == sorted(attacked)


def _without_props(xml: str) -> str:
    return re.sub(r'\s*<shape type="\w+" id="prop_\d+">.*?</shape>', "", xml, flags=re.S)


def _props(xml: str) -> list[str]:
    return re.findall(r'<shape type="\w+" id="prop_\d+">.*?</shape>', xml, flags=re.S)


def test_each_condition_renders_its_own_scene_in_one_place(local_run, inputs):
    """A condition's frames are its scene's (cameras, weather, light, object); the background props are
    placed once for the run, the same in every condition (one park, seen under every condition)."""
    from undream.scenedir.conditions import grid_sequences
    from undream.scenedir.init import InitOptions, init_scene

    (name, seq), = [(n, s) for n, s in grid_sequences(inputs["spec"], GRID) if n == NAMES[2]]
    alone = init_scene(seq, inputs["root"] / "alone", InitOptions(verify_spp=1))
    frames = local_run["out"] / "scene" / "frames"
    for k in range(4):  # condition 2's frames are 8..11 of the run
        for kind in ("sim", "grad"):
            mine, theirs = ((d / f"{kind}_{i:04d}.xml").read_text() for d, i in ((frames, 8 + k), (alone / "frames", k)))
            assert _without_props(mine) == _without_props(theirs)
    props = [_props((frames / f"sim_{i:04d}.xml").read_text()) for i in range(16)]
    assert props[0] and all(p == props[0] for p in props)  # the park's props are there, and never move


def test_scenes_of_one_object_make_a_run_and_a_scene_directory_is_one(inputs):
    """``conditions.scenes``: spec files and scene directories, each a condition named by its file."""
    root = inputs["root"]
    night = write_yaml(root / "night.yaml", {**SPEC, "environment": {"weather": "night", "time_of_day": 22.0}})
    street = _undream("init", write_yaml(root / "street.yaml", {**SPEC, "environment": {"background": "street"}}),
                      "--out", root / "street_scene", "--no-progress")
    assert street.returncode == 0, street.stderr
    cfg = _config(inputs, "scenes", holdout="none",
                  conditions={"scenes": [str(night), str(root / "street_scene")], "holdout": ["street_scene"]})
    out = root / "out_scenes"
    res = _undream("run", write_yaml(root / "scenes.yaml", cfg), "--out", out, "--no-progress")
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    assert [r["name"] for r in results["conditions"]] == ["ball", "night", "street_scene"]
    assert results["attacked"]["frames"] == list(range(8)) and results["held_out"] is None
    assert results["held_out_conditions"]["frames"] == [8, 9, 10, 11]


def test_a_grid_over_a_vector_field_moves_it_per_condition(inputs):
    """A grid value may be a list of numbers: each condition's frames carry that vector (here the
    night lamp), the name spells it, and the run config's JSON round trip keeps it."""
    from undream.scenedir.conditions import conditions_sequence
    from undream.spec.run import RunConfig

    lamps = [[1.0, 5.0, 2.0], [-2.5, 6.0, 1.5]]
    cfg = RunConfig.from_json(_config(inputs, "lamps", conditions={
        "grid": {"environment.weather": ["night"], "environment.lamp_offset": lamps}}))
    assert RunConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    seq = conditions_sequence(cfg, ROOT)
    assert [c.name for c in seq.conditions] == ["weather_night-lamp_offset_1p0_5p0_2p0",
                                                "weather_night-lamp_offset_-2p5_6p0_1p5"]
    per_frame = [tuple(f.environment.lamp_offset) for f in seq.frames]
    assert per_frame == [tuple(lamps[0])] * 4 + [tuple(lamps[1])] * 4


def test_grids_join_products_that_one_grid_would_multiply(inputs):
    """``conditions.grids``: each grid a product of its own values, their conditions after ``grid``'s
    (nights under two lamps beside days under two weathers: 4 conditions, not the 2 × 2 × 2 of one
    grid), each condition's frames carrying its own values, and the JSON round trip keeps them."""
    from undream.scenedir.conditions import conditions_sequence
    from undream.spec.run import RunConfig

    lamps = [[1.0, 5.0, 2.0], [-2.5, 6.0, 1.5]]
    cfg = RunConfig.from_json(_config(inputs, "joined", conditions={
        "grid": {"environment.weather": ["night"], "environment.lamp_offset": lamps},
        "grids": [{"environment.weather": ["clear", "fog"]}], "holdout": ["weather_fog"]}))
    assert RunConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    seq = conditions_sequence(cfg, ROOT)
    assert [c.name for c in seq.conditions] == ["weather_night-lamp_offset_1p0_5p0_2p0",
                                                "weather_night-lamp_offset_-2p5_6p0_1p5", "weather_clear",
                                                "weather_fog"]
    assert [f.environment.weather for f in seq.frames] == ["night"] * 8 + ["clear"] * 4 + ["fog"] * 4
    grids_only = RunConfig.from_json(_config(inputs, "grids", conditions={"grids": [GRID]}))
    assert [c.name for c in conditions_sequence(grids_only, ROOT).conditions] == NAMES  # `scene` is not one
    out = inputs["root"] / "joined"  # and through `undream run`: the held-out grid condition is never attacked
    (inputs["root"] / "joined.yaml").write_text(yaml.safe_dump(cfg.to_json(), sort_keys=False))  # names follow key order
    res = _undream("run", inputs["root"] / "joined.yaml", "--out", out, "--no-progress")
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    assert [r["name"] for r in results["conditions"]] == [c.name for c in seq.conditions]
    assert results["held_out_conditions"]["frames"] == [12, 13, 14, 15]
    assert results["attacked"]["frames"] == [0, 1, 2, 4, 5, 6, 8, 9, 10]


@pytest.mark.parametrize("conditions, expected", [
    ({"grid": GRID, "grids": [GRID]}, "conditions: two conditions are named height_0p6-weather_clear"),
    ({"grids": {"environment.weather": ["fog"]}}, "conditions.grids: must be a list of grids"),
    ({"grids": [{}]}, "conditions.grids[0]: must name at least one field"),
    ({"grids": [{"environment.weather": ["fog"]}, {"camera.path.height": [0.6, 0.6]}]},
     "conditions.grids[1].camera.path.height: must not repeat a value"),
    ({"grids": [{"camera.path.height": ["high"]}]}, "conditions.grids[0] (height_high)"),
    ({"scenes": ["cone.yaml"]}, "condition 'cone': its object (builtin:traffic_cone"),
    ({"scenes": ["big.yaml"]}, "condition 'big': its texture (adv_texture, 32×8"),
    ({"grid": GRID, "holdout": ["weather_snow"]}, "conditions.holdout: 'weather_snow' is not a condition"),
    ({"grid": {"environment.wether": ["clear"]}}, "wether"),
    ({"grid": {"camera.path.height": []}}, "conditions.grid.camera.path.height: must be a non-empty list"),
    ({"grid": GRID, "holdout": NAMES}, "conditions.holdout"),
    ({"scenes": ["missing.yaml"]}, "conditions.scenes[0]"),
    ({"grid": {"environment.lamp_offset": [[1, "x", 2]]}},
     "conditions.grid.environment.lamp_offset: values must be strings, numbers or lists of numbers, got [1, 'x', 2]"),
    # more combinations than a run's frames: refused from the counts, before one spec is built (it was after
    # every one of them, which for a grid of millions took hours before the frame bound's error)
    ({"grid": {f: [0.5 + i / 10 for i in range(11)] for f in
               ("camera.path.height", "camera.path.radius", "camera.fov", "environment.time_of_day")}},
     "conditions: 14,641 conditions (conditions.grid 14,641) is more than a run's 10,000 frames"),
    ({"grid": GRID, "grids": [{"camera.path.height": list(range(1, 101)), "camera.path.radius": list(range(1, 101))}],
      "scenes": ["cone.yaml"]},
     "conditions: 10,005 conditions (conditions.grid 4, conditions.grids[0] 10,000) is more than"),
])
def test_bad_conditions_are_refused_in_one_line_before_anything_is_written(inputs, conditions, expected):
    root = inputs["root"]
    write_yaml(root / "cone.yaml", {**SPEC, "object": {**SPEC["object"], "asset": {
        **SPEC["object"]["asset"], "mesh": "builtin:traffic_cone"}}})
    write_yaml(root / "big.yaml", {**SPEC, "object": {**SPEC["object"], "asset": {
        **SPEC["object"]["asset"], "texture": {"resolution": [32, 8]}}}})
    out = root / "refused"
    res = _undream("run", write_yaml(root / "bad.yaml", _config(inputs, "bad", conditions=conditions)),
                   "--out", out, "--no-progress", cwd=root)
    assert res.returncode != 0
    message = res.stderr.strip()
    assert expected in message and len(message.splitlines()) == 1, message
    assert not out.exists()


def test_a_grid_needs_a_spec_file(tmp_path, inputs):
    scene = make_scene(tmp_path / "scene", n_frames=2, size=16)
    cfg = _config(inputs, "dir", conditions={"grid": GRID})
    cfg["scene"] = str(scene)
    res = _undream("run", write_yaml(tmp_path / "run.yaml", cfg), "--out", tmp_path / "out", "--no-progress")
    assert res.returncode != 0 and "conditions.grid: needs scene to be a YAML spec file" in res.stderr


def test_a_grid_over_a_spec_whose_texture_is_an_image_finds_it_beside_the_spec(tmp_path, inputs):
    """The spec names its starting texture relative to its own folder; the grid's conditions must
    find it there, not beside the run config or the working directory."""
    spec_dir = tmp_path / "specs"
    (spec_dir / "textures").mkdir(parents=True)
    Image.new("RGB", (16, 8), (180, 20, 30)).save(spec_dir / "textures" / "start.png")
    spec = yaml.safe_load(inputs["spec"].read_text())
    spec["object"]["asset"]["texture"]["init"] = "textures/start.png"
    cfg = _config(inputs, "image_start")
    cfg["scene"] = str(write_yaml(spec_dir / "ball.yaml", spec))
    res = _undream("run", write_yaml(tmp_path / "run.yaml", cfg), "--out", tmp_path / "out", "--check")
    assert res.returncode == 0, res.stderr
    assert not (tmp_path / "out").exists()


def test_a_multi_condition_run_on_the_farm_ends_on_the_local_runs_texture(inputs, local_run):
    reason = redis_up()
    if reason:
        service_missing(reason)
    farm = Farm(inputs["root"] / "farm")
    farm.root.mkdir()
    try:
        farm.start_worker()
        run_id = farm.submit(write_yaml(farm.root / "grid.yaml", _config(inputs, "grid")))
        run = farm.wait_status(run_id, timeout=180)
        assert run.status == "done", run.error
        assert {j.frame for j in farm.store.jobs(run_id, None, "attack")} == {0, 1, 2, 4, 5, 6, 8, 9, 10}
        out = farm.blobs / "outputs" / f"grid-{run_id[:8]}"
        assert np.array_equal(np.load(out / "texture_final.npy"), np.load(local_run["out"] / "texture_final.npy"))
        held = json.loads((out / "results.json").read_text())["held_out_conditions"]
        assert held == local_run["results"]["held_out_conditions"]
    finally:
        farm.stop()


def test_the_report_shows_the_runs_transfer_to_its_conditions(local_run, tmp_path):
    import csv
    import io

    res = _undream("report", local_run["out"], "--out", tmp_path / "report")
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader(io.StringIO((tmp_path / "report" / "conditions.csv").read_text())))
    assert [r["condition"] for r in rows] == NAMES
    assert [r["held_out"] for r in rows] == ["False", "False", "False", "True"]
    held = local_run["results"]["held_out_conditions"]["adversarial"]["value"]
    assert float(rows[3]["adversarial"]) == pytest.approx(held)
    page = (tmp_path / "report" / "index.html").read_text()
    assert "<h2>Conditions</h2>" in page and "held-out conditions" in page and NAMES[3] in page
    headline = (tmp_path / "report" / "headline.csv").read_text()
    assert "held-out conditions" in headline
    assert "held-out conditions (4)" in local_run["stdout"]


def test_a_sequences_conditions_round_trip_and_must_hold_its_frames(local_run):
    from dataclasses import replace

    from undream.errors import SpecError
    from undream.spec import Condition, Sequence, load_sequence

    seq = load_sequence(local_run["out"] / "scene" / "sequence.json")
    assert Sequence.from_json(seq.to_json()) == seq
    with pytest.raises(SpecError, match="must hold the 16 frames between them"):
        replace(seq, conditions=seq.conditions[:3])
    with pytest.raises(SpecError, match="unique names"):
        replace(seq, conditions=(Condition("a", 8), Condition("a", 8)))
    alone = replace(seq, conditions=())
    assert "conditions" not in alone.to_json()  # a sequence of one scene: its file as before


def test_a_minibatched_run_captures_each_frame_about_every_refresh_uses(local_run):
    from undream.engine.context import refresh_iterations
    from undream.spec import load_sequence
    from undream.spec.run import RunConfig

    seq = load_sequence(local_run["out"] / "scene" / "sequence.json")
    full = RunConfig(scene="s", conditions={"grid": GRID, "holdout": [NAMES[3]]}, transport_refresh=5)
    assert refresh_iterations(full, seq) == 5  # every attacked frame each iteration
    mini = RunConfig(scene="s", conditions={"grid": GRID, "holdout": [NAMES[3]]}, transport_refresh=5,
                     attack={"name": "pgd", "frames_per_step": 2})
    assert refresh_iterations(mini, seq) == 5 * 5  # 9 attacked frames, 2 per iteration: 5 iterations a pass


def test_undream_evaluate_judges_a_multi_condition_scene_per_condition(local_run, tmp_path):
    out = tmp_path / "rows.json"
    res = _undream("evaluate", local_run["out"], local_run["out"] / "scene", "--victim",
                   local_run["results"]["victim"], "--spp", 2, "--json", out, "--frames-csv", tmp_path / "frames.csv")
    assert res.returncode == 0, res.stderr
    rows = {r["split"]: r for r in json.loads(out.read_text())["rows"]}
    assert [s for s in rows if s.startswith("condition ")] == [f"condition {n}" for n in NAMES]
    assert rows[f"condition {NAMES[1]}"]["frames"] == 4 and rows["all"]["frames"] == 16
    assert rows["held_out"]["frames"] == 4  # each condition's 4th view
    # one row per frame, named by its condition, each condition's 4th view held out
    frames = list(csv.DictReader((tmp_path / "frames.csv").open()))
    assert [f["condition"] for f in frames] == [n for n in NAMES for _ in range(4)]
    assert [f["split"] for f in frames[:4]] == ["attacked"] * 3 + ["held_out"]
    for n in NAMES:
        right = [f["texture_correct"] == "True" for f in frames if f["condition"] == n]
        assert sum(right) / 4 == pytest.approx(rows[f"condition {n}"]["adversarial"])


def test_a_condition_in_which_the_object_is_never_seen_is_refused_naming_it(inputs, tmp_path):
    """Issue 41: a condition whose camera looks away from the object was attacked anyway (the other
    conditions showed it) and reported 0.0 → 0.0. Now `undream run` refuses it in one line naming the
    condition, after its masks are rendered and before the run is recorded; --out is left absent."""
    cfg = run_config(inputs["spec"], inputs["victim"], name="unseen", steps=1)
    cfg["conditions"] = {"grid": {"camera.look_at_offset": [[0, 0.4, 0], [0, 60, 0]]}}
    out = tmp_path / "out"
    check = _undream("run", write_yaml(tmp_path / "unseen.yaml", cfg), "--out", out, "--check")
    assert check.returncode == 0, check.stderr  # --check renders no masks, and says it did not look
    assert "whether a frame (of each condition) shows the object is checked when its masks are rendered, " \
           "not by --check" in check.stdout, check.stdout
    res = _undream("run", tmp_path / "unseen.yaml", "--out", out, "--no-progress")
    assert res.returncode == 2, res.stderr[-3000:]
    line = res.stderr.strip()
    assert "\n" not in line and line.startswith("undream: error: condition 'look_at_offset_0_60_0': "), line
    assert "the object is visible in 0 of 4 frames" in line, line
    assert not out.exists()
