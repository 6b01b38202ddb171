"""Input limits: every bound stated once (undream.spec.limits), every file read by one strict reader.

Before (issue 19, each reproduced on main): a duplicate YAML key silently won
(``attack: {eps: 8, eps: 255}`` ran at 255); ε of 300, a billion attack steps
and ``frames: 99999`` were accepted (the last ran until killed); a zero or
view-parallel camera ``up`` was ignored; a camera inside the object ran to
"benign 0.000 → adversarial 0.000" with exit 0; numbers of thousands of
digits, deep nesting and an alias bomb were tracebacks (the bomb after
minutes and gigabytes), and ``--out`` under /proc was a traceback.

Each case runs the real command in-process (click's runner on
``undream.cli.main``) and expects exit 2, one stderr line naming the
file, the field or line and the bound, no OUT, and the inputs byte-identical.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from PIL import Image

from farm_support import make_scene
from undream.cli import main

ROOT = Path(__file__).resolve().parents[1]
SPEC = {"name": "limits", "frames": 2,
        "camera": {"fov": 40, "resolution": [16, 16], "path": {"type": "static", "position": [0, 1, 4]}},
        "object": {"asset": {"name": "ball", "mesh": "builtin:sphere"},
                   "path": {"type": "static", "position": [0, 0, 0]}}}
BOMB = "\n".join(["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
                 + [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 10)])


def _write(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return path


def _run_doc(scene: str, **attack) -> dict:
    return {"name": "limits", "scene": scene, "victim": "bundled:classifier", "loss": "ce",
            "attack": {"name": "pgd", "eps": 8, "steps": 1, **attack}, "sim_spp": 1, "grad_spp": 1, "eval_spp": 1}


def _refused(args: list[str], inputs: list[Path], out: Path, *needles: str, within: float | None = None) -> str:
    """Run ``undream ARGS``: exit 2, one line holding every needle, ``out`` absent, inputs unchanged;
    ``within``: at most that many seconds of this process's CPU time (the work the refusal did; wall
    time also counts whatever else the machine runs, such as the other pytest-xdist process)."""
    before = {p: p.read_bytes() for p in inputs}
    start = time.process_time()
    res = CliRunner().invoke(main, args)
    took = time.process_time() - start
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert res.exit_code == 2, (res.exit_code, res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("undream: error: "), res.stderr[-3000:]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert not out.exists(), sorted(out.rglob("*"))
    assert {p: p.read_bytes() for p in inputs} == before
    if within is not None:
        assert took < within, f"took {took:.1f} s of CPU time"
    return lines[0]


def _init(spec: Path, out: Path, *needles: str, within: float | None = None) -> str:
    return _refused(["init", str(spec), "--out", str(out), "--verify-spp", "1", "--no-progress"], [spec], out,
                    str(spec.name), *needles, within=within)


def _run(cfg: Path, out: Path, *needles: str, within: float | None = None, inputs: tuple[Path, ...] = ()) -> str:
    return _refused(["run", str(cfg), "--out", str(out), "--no-progress"], [cfg, *inputs], out, cfg.name,
                    *needles, within=within)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_scene(tmp_path_factory.mktemp("limits") / "scene", n_frames=2, size=16)


# -- duplicate keys ----------------------------------------------------------------------------------


def test_a_duplicate_key_in_a_run_config_is_refused_naming_key_and_lines(tmp_path, scene):
    text = yaml.safe_dump(_run_doc(str(scene)), sort_keys=False).replace("eps: 8", "eps: 8\n  eps: 255")
    cfg = _write(tmp_path / "run.yaml", text)
    line = _run(cfg, tmp_path / "out", "duplicate key 'eps'", "line")
    assert "first at line" in line


def test_a_duplicate_key_in_a_spec_is_refused(tmp_path):
    text = yaml.safe_dump(SPEC, sort_keys=False) + "frames: 3\n"
    spec = _write(tmp_path / "spec.yaml", text)
    _init(spec, tmp_path / "out", "duplicate key 'frames'", f"line {text.count(chr(10))}", "first at line 2")


def test_a_duplicate_key_in_a_sweep_file_is_refused_before_any_service(tmp_path, scene):
    _write(tmp_path / "run.yaml", _run_doc(str(scene)))
    sweep = _write(tmp_path / "sweep.yaml", "name: s\nrun: run.yaml\ngrid:\n  seed: [0, 1]\n  seed: [2]\n")
    _refused(["sweep", str(sweep), "--out", str(tmp_path / "out"), "--broker", "redis://127.0.0.1:1/0"],
             [sweep], tmp_path / "out", "sweep.yaml", "line 5", "duplicate key 'seed'")


def test_a_duplicate_key_in_a_settings_file_is_refused(tmp_path, scene):
    cfg = _write(tmp_path / "run.yaml", _run_doc(str(scene)))
    settings = _write(tmp_path / "settings.yaml", "broker_url: redis://a:1/0\nbroker_url: redis://b:1/0\n")
    _refused(["submit", str(cfg), "--check", "--settings", str(settings)], [cfg, settings], tmp_path / "out",
             "settings.yaml", "line 2", "duplicate key 'broker_url'")


def test_a_duplicate_key_in_a_sequence_json_is_refused(tmp_path):
    from undream.scene.trajectory import sequence_from_trajectory

    text = json.dumps(sequence_from_trajectory(SPEC).to_json(), indent=1)
    spec = _write(tmp_path / "sequence.json", text.replace('"fps": 10.0,', '"fps": 10.0,\n "fps": 99,', 1))
    _init(spec, tmp_path / "out", "duplicate key 'fps'", "line")


def test_a_duplicate_key_in_an_unreal_export_is_refused(tmp_path):
    text = (ROOT / "examples" / "unreal" / "drive_by_export.json").read_text()
    spec = _write(tmp_path / "ue.json", text.replace("{", '{"fps": 1,\n', 1))
    _init(spec, tmp_path / "out", "duplicate key 'fps'", "line")


# -- ranges --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("attack, needles", [
    ({"eps": 300}, ["attack.eps: 300 is out of range", "0 < eps ≤ 255"]),
    ({"steps": 10**9}, ["attack.steps: 1000000000 is out of range", "1 ≤ steps ≤ 100000"]),
    ({"step_size": 1000}, ["attack.step_size", "≤ 255"]),
    ({"seed": 2**70}, ["attack.seed", "out of range"]),
    ({"frames_per_step": 10**6}, ["attack.frames_per_step", "≤ 10000"]),
])
def test_attack_numbers_out_of_range_are_refused_with_the_bound(attack, needles, tmp_path, scene):
    cfg = _write(tmp_path / "run.yaml", _run_doc(str(scene), **attack))
    _run(cfg, tmp_path / "out", *needles)


def test_absurd_frame_counts_are_refused_at_once(tmp_path):
    spec = _write(tmp_path / "spec.yaml", {**SPEC, "frames": 99999})
    _init(spec, tmp_path / "out", "frames: 99999 is out of range", "1 ≤ frames ≤ 10000", within=5)


def test_a_sequence_json_of_too_many_frames_is_refused_at_once(tmp_path):
    from undream.scene.trajectory import sequence_from_trajectory

    doc = sequence_from_trajectory(SPEC).to_json()
    doc["frames"] = [{**doc["frames"][0], "index": i} for i in range(10001)]
    spec = _write(tmp_path / "sequence.json", json.dumps(doc))
    _init(spec, tmp_path / "out", "frames", "10001", "10000", within=5)


def test_run_config_numbers_name_their_bound(tmp_path, scene):
    cfg = _write(tmp_path / "run.yaml", {**_run_doc(str(scene)), "sim_spp": 10**6})
    _run(cfg, tmp_path / "out", "sim_spp: 1000000 is out of range", "1 ≤ sim_spp ≤ 65536")


def test_a_sweep_grid_beyond_the_cap_is_refused_before_expanding(tmp_path, scene):
    _write(tmp_path / "run.yaml", _run_doc(str(scene)))
    sweep = _write(tmp_path / "sweep.yaml", {"name": "s", "run": "run.yaml",
                                             "grid": {"seed": list(range(101)), "attack.steps": list(range(1, 101))}})
    _refused(["sweep", str(sweep), "--check"], [sweep], tmp_path / "out", "sweep.yaml", "10100 runs",
             "cap of 10000", "--max-runs", within=5)
    _refused(["sweep", str(sweep), "--check", "--max-runs", "50"], [sweep], tmp_path / "out", "cap of 50")


# -- numbers that are not numbers ----------------------------------------------------------------------


def test_a_number_of_thousands_of_digits_is_one_line(tmp_path, scene):
    text = yaml.safe_dump(_run_doc(str(scene)), sort_keys=False).replace("eps: 8", "eps: 1" + "0" * 5000)
    cfg = _write(tmp_path / "run.yaml", text)
    _run(cfg, tmp_path / "out", "eps", "5001 digits", "is not a number in range", "line")


def test_an_int_too_big_for_a_float_is_one_line(tmp_path):
    text = yaml.safe_dump(SPEC, sort_keys=False).replace("fov: 40", "fov: 1" + "0" * 400)
    spec = _write(tmp_path / "spec.yaml", text)
    _init(spec, tmp_path / "out", "fov", "401 digits", "is not a number in range")


def test_a_json_number_of_thousands_of_digits_is_one_line(tmp_path):
    from undream.scene.trajectory import sequence_from_trajectory

    text = json.dumps(sequence_from_trajectory(SPEC).to_json(), indent=1)
    spec = _write(tmp_path / "sequence.json", text.replace('"seed": 0', '"seed": 9' + "9" * 6000, 1))
    _init(spec, tmp_path / "out", "6001 digits", "is not a number in range", "line")


def test_an_int_between_float_range_and_the_digit_limit_names_the_field(tmp_path):
    spec = _write(tmp_path / "spec.yaml", yaml.safe_dump(SPEC, sort_keys=False).replace("fov: 40", f"fov: {10**90}"))
    _init(spec, tmp_path / "out", "camera.fov", "(0, 180)")


# -- files that expand -----------------------------------------------------------------------------------


def test_an_alias_bomb_is_refused_within_seconds(tmp_path, scene):
    cfg = _write(tmp_path / "run.yaml", BOMB + "\n" + yaml.safe_dump(_run_doc(str(scene)), sort_keys=False)
                 .replace("name: limits", "name: *a9"))
    _run(cfg, tmp_path / "out", "alias", "1000000", within=5)


def test_an_alias_bomb_in_a_spec_is_refused_within_seconds(tmp_path):
    spec = _write(tmp_path / "spec.yaml", BOMB + "\n" + yaml.safe_dump({**SPEC, "name": "NAME"}, sort_keys=False)
                  .replace("name: NAME", "name: *a9"))
    _init(spec, tmp_path / "out", "alias", "1000000", within=5)


def test_a_self_referencing_alias_is_refused(tmp_path):
    text = yaml.safe_dump(SPEC, sort_keys=False) + "loop: &l [*l]\n"
    spec = _write(tmp_path / "spec.yaml", text)
    _init(spec, tmp_path / "out", "alias *l", f"line {text.count(chr(10))}")


def test_deep_nesting_is_refused_within_seconds(tmp_path, scene):
    cfg = _write(tmp_path / "run.yaml", yaml.safe_dump(_run_doc(str(scene)), sort_keys=False)
                 + "eot: " + "[" * 50000 + "]" * 50000 + "\n")
    _run(cfg, tmp_path / "out", "nested deeper than 64", "line", within=5)


def test_deep_json_nesting_is_refused_within_seconds(tmp_path):
    spec = _write(tmp_path / "sequence.json", '{"frames": ' + "[" * 100000 + "]" * 100000 + "}")
    _init(spec, tmp_path / "out", "nested deeper than 64", within=5)


def test_a_file_larger_than_the_limit_is_refused_unread(tmp_path):
    spec = _write(tmp_path / "spec.yaml", yaml.safe_dump(SPEC) + ("# padding\n" * 120_000))
    _init(spec, tmp_path / "out", "bytes", "at most 1048576", within=5)


# -- cameras ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("up, position, needles", [
    ([0, 0, 0], [0, 1, 4], ["camera.up", "non-zero"]),
    ([0, 1, 0], [0, 5, 0], ["camera.up", "frame 0", "parallel"]),
    ([0, 2, 0], [0, 5, 0], ["camera.up", "frame 0", "parallel"]),
    ([0, 1, "x"], [0, 1, 4], ["camera.up[2]", "number"]),
])
def test_a_degenerate_camera_up_is_refused(up, position, needles, tmp_path):
    spec = _write(tmp_path / "spec.yaml", {**SPEC, "camera": {**SPEC["camera"], "up": up,
                                                              "path": {"type": "static", "position": position}}})
    _init(spec, tmp_path / "out", *needles)


def test_a_camera_up_is_used():
    from undream.scene.trajectory import sequence_from_trajectory

    tilted = sequence_from_trajectory({**SPEC, "camera": {**SPEC["camera"], "up": [1, 0, 0]}})
    upright = sequence_from_trajectory(SPEC)
    y_axis = lambda seq: np.array(seq.frames[0].camera.to_world.matrix)[:3, 1]  # noqa: E731
    assert y_axis(upright)[1] > 0.9 and abs(y_axis(tilted)[0]) > 0.9


@pytest.mark.parametrize("camera", [
    {"path": {"type": "static", "position": [0, 0.5, 0.1]}, "look_at": [0, 0.5, 5]},  # inside the ball
    {"path": {"type": "static", "position": [0, 1, 4]}, "look_at": [0, 1, 10]},  # looking away
])
def test_an_object_seen_in_no_frame_is_refused_at_init(camera, tmp_path):
    spec = _write(tmp_path / "spec.yaml", {**SPEC, "camera": {**SPEC["camera"], **camera}})
    _init(spec, tmp_path / "out", "the object is visible in 0 of 2 frames", "nothing written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


def test_a_run_on_a_scene_that_never_shows_the_object_is_refused(tmp_path, scene):
    blind = tmp_path / "blind"
    import shutil

    shutil.copytree(scene, blind)
    for mask in sorted((blind / "verify").glob("mask_*.png")):
        Image.fromarray(np.zeros_like(np.asarray(Image.open(mask)))).save(mask)
    cfg = _write(tmp_path / "run.yaml", _run_doc(str(blind)))
    _run(cfg, tmp_path / "out", "the object is visible in 0 of 2 frames", "verify/mask_")


# -- output folders ---------------------------------------------------------------------------------------


def test_an_out_under_proc_is_one_line(tmp_path):
    spec = _write(tmp_path / "spec.yaml", SPEC)
    _refused(["init", str(spec), "--out", "/proc/undream-limits", "--verify-spp", "1", "--no-progress"], [spec],
             Path("/proc/undream-limits"), "/proc")


def test_the_limits_page_lists_every_bound_as_the_schema_states_it():
    """docs/safety.md's table is the schema's BOUNDS, row for row: a bound changed in one place only
    fails here."""
    import re
    from undream.spec.limits import BOUNDS

    page = (Path(__file__).resolve().parents[1] / "docs" / "safety.md").read_text(encoding="utf-8")
    table = page.split("<!-- bounds:", 1)[1].split("<!-- /bounds -->", 1)[0]
    rows = dict(re.findall(r"^\| `([^`]+)` \| (.+?) \|$", table, re.MULTILINE))
    assert rows == {field: bound.describe(field.rsplit(".", 1)[-1]) for field, bound in BOUNDS.items()}
