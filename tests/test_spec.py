"""The spec layer: validation, JSON round trip, and no heavy imports."""
import json
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from undream.errors import SpecError
from undream.spec import (
    ActorPose, Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform,
    load_sequence, save_sequence, sun_direction,
)


def _seq(**frame_kw):
    cam = Camera(Transform.identity(), 45.0, (64, 48))
    frames = (Frame(0, cam, Transform.identity(), **frame_kw), Frame(1, cam, Transform.identity(), time=0.1))
    return Sequence("s", Asset("obj", "builtin:sphere", texture=TextureParam()), frames)


def test_spec_imports_nothing_heavy():
    code = ("import sys, undream.spec, undream.spec.io; "
            "heavy = [m for m in ('mitsuba', 'drjit', 'torch', 'celery', 'sqlalchemy') if m in sys.modules]; "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_json_round_trip_is_exact(tmp_path):
    seq = Sequence("s", Asset("obj", "builtin:car", scale=2.0,
                              texture=TextureParam("skin", (32, 64), (3.0, 2.0), "tex.png")),
                   (Frame(0, Camera(Transform.identity(), 60.0, (64, 36), film=(64, 43)), Transform.identity(),
                          Environment("fog", 7.5, "park"), (ActorPose("car2", Transform.identity()),)),),
                   actors=(Asset("car2", "builtin:car", color=(0.7, 0.1, 0.1)),), fps=30.0, seed=7)
    save_sequence(seq, tmp_path / "sequence.json")
    assert load_sequence(tmp_path / "sequence.json") == seq
    assert Sequence.from_json(json.loads(json.dumps(seq.to_json()))) == seq


@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3), st.floats(1.0, 179.0),
       st.integers(1, 4096), st.integers(1, 4096))
@settings(max_examples=50, deadline=None)
def test_camera_round_trip_property(t, fov, w, h):
    m = ((1, 0, 0, t[0]), (0, 1, 0, t[1]), (0, 0, 1, t[2]), (0, 0, 0, 1))
    cam = Camera(Transform(m), fov, (w, h))
    assert Camera.from_json(json.loads(json.dumps(cam.to_json()))) == cam


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d["frames"][0]["camera"].__setitem__("fov_deg", 190), "frames[0].camera.fov_deg"),
    (lambda d: d["frames"][0]["object_to_world"][1].__setitem__(3, float("nan")),
     "frames[0].object_to_world.matrix[1][3]"),
    (lambda d: d["frames"][1]["camera"].__setitem__("resolution", [64]), "frames[1].camera.resolution"),
    (lambda d: d["frames"][0]["environment"].__setitem__("weather", "hail"), "frames[0].environment.weather"),
    (lambda d: d["asset"].__setitem__("mesh", "thing.fbx"), "asset.mesh"),
    (lambda d: d["frames"][1].__setitem__("index", 0), "frames"),
    (lambda d: d["frames"][0]["camera"]["to_world"][0].__setitem__(0, 2.0), "frames[0].camera.to_world"),
    (lambda d: d["asset"]["texture"].__setitem__("resolution", [0, 8]), "asset.texture.resolution[0]"),
    (lambda d: d.__setitem__("colour", 1), "colour"),
])
def test_bad_fields_are_named(mutate, field):
    d = _seq().to_json()
    mutate(d)
    with pytest.raises(SpecError) as err:
        Sequence.from_json(d)
    assert str(err.value).startswith(field), str(err.value)
    assert "\n" not in str(err.value)


def test_load_sequence_names_the_file(tmp_path):
    p = tmp_path / "sequence.json"
    p.write_text("{ not json")
    with pytest.raises(SpecError, match=r"sequence.json: line 1 column 3: not valid JSON"):
        load_sequence(p)
    with pytest.raises(SpecError, match="missing.json: file not found"):
        load_sequence(tmp_path / "missing.json")


def test_unknown_actor_in_frame_is_rejected():
    with pytest.raises(SpecError, match="unknown actor 'ghost'"):
        _seq(actors=(ActorPose("ghost", Transform.identity()),))


@pytest.mark.parametrize("hour, expect_up", [(12.0, True), (9.0, True), (3.0, False), (21.0, False)])
def test_sun_is_up_by_day_only(hour, expect_up):
    d, elev = sun_direction(Environment(time_of_day=hour))
    assert abs(sum(x * x for x in d) - 1) < 1e-9
    assert (elev > 0) == expect_up
    assert (d[1] > 0) == expect_up


def test_noon_sun_is_in_the_south_at_max_elevation():
    d, elev = sun_direction(Environment(time_of_day=12.0, sun_max_elevation_deg=55.0))
    assert elev == pytest.approx(55.0)
    assert d[0] == pytest.approx(0.0, abs=1e-9) and d[2] < 0
