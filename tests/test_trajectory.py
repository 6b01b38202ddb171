"""Native trajectory specs → canonical sequences."""
import numpy as np
import pytest
import yaml

from undream.errors import SpecError
from undream.scene.sources import sequence_from_file
from undream.scene.trajectory import sequence_from_trajectory


def _spec(camera_path, object_path=None, n=5, **extra):
    obj = {"asset": {"name": "thing", "mesh": "builtin:sphere"}}
    if object_path is not None:
        obj["path"] = object_path
    return {"name": "t", "frames": n, "camera": {"fov": 50, "resolution": [32, 24], "path": camera_path},
            "object": obj, **extra}


def _m(t):
    return np.array(t.matrix)


def test_orbit_keeps_radius_and_looks_at_the_object():
    seq = sequence_from_trajectory(_spec({"type": "orbit", "center": [1, 0, 2], "radius": 4, "height": 1.5,
                                          "start_deg": 0, "end_deg": 180}, n=7))
    for f in seq.frames:
        cam = _m(f.camera.to_world)
        pos = cam[:3, 3]
        assert np.hypot(pos[0] - 1, pos[2] - 2) == pytest.approx(4.0)
        assert pos[1] == pytest.approx(1.5)
        target = np.array([0, 0.5, 0])  # object origin + default look_at_offset
        d = (target - pos) / np.linalg.norm(target - pos)
        assert cam[:3, 2] == pytest.approx(d)
        assert f.camera.to_world.is_rigid()
    # 0° is +Z of the centre, 180° is -Z
    assert _m(seq.frames[0].camera.to_world)[:3, 3] == pytest.approx([1, 1.5, 6])
    assert _m(seq.frames[-1].camera.to_world)[:3, 3] == pytest.approx([1, 1.5, -2])


def test_image_left_is_camera_x():
    """Mitsuba's camera: +X points to the image's left, +Y up."""
    seq = sequence_from_trajectory(_spec({"type": "static", "position": [0, 0.5, 5]}, n=1))
    cam = _m(seq.frames[0].camera.to_world)
    assert cam[:3, 2] == pytest.approx([0, 0, -1])  # looking along -Z towards the origin
    assert cam[:3, 1] == pytest.approx([0, 1, 0])
    assert cam[:3, 0] == pytest.approx([-1, 0, 0])  # left of the image is world -X from here


def test_flyover_straight_down_is_exact_and_rigid():
    seq = sequence_from_trajectory(_spec({"type": "flyover", "start": [-4, 0, 0], "end": [4, 0, 0], "altitude": 10},
                                         n=5, ))
    mid = _m(seq.frames[2].camera.to_world)
    assert mid[:3, 3] == pytest.approx([0, 10, 0])
    assert mid[:3, 2] == pytest.approx([0, -1, 0], abs=1e-12)  # straight down
    assert seq.frames[2].camera.to_world.is_rigid()


def test_drive_by_heads_along_motion():
    seq = sequence_from_trajectory(_spec({"type": "static", "position": [0, 2, 12]},
                                         {"type": "drive_by", "start": [-5, 0, 0], "end": [5, 0, 0]}))
    for f in seq.frames:
        front = _m(f.object_to_world)[:3, 2]
        assert front == pytest.approx([1, 0, 0], abs=1e-9)
    xs = [f.object_to_world.translation[0] for f in seq.frames]
    assert xs == pytest.approx(np.linspace(-5, 5, 5))


def test_keyframes_pass_through_keys_and_are_smooth():
    keys = [{"frame": 0, "position": [0, 1, 5]}, {"frame": 4, "position": [3, 2, 4]},
            {"frame": 8, "position": [0, 1, 3]}]
    seq = sequence_from_trajectory(_spec({"type": "keyframes", "keys": keys}, n=9))
    pos = np.array([_m(f.camera.to_world)[:3, 3] for f in seq.frames])
    for k in keys:
        assert pos[k["frame"]] == pytest.approx(k["position"])
    # cubic, not a linear ramp: frame 2 lies off the straight segment between keys 0 and 4
    assert not np.allclose(pos[2], (pos[0] + pos[4]) / 2)
    lin = sequence_from_trajectory(_spec({"type": "keyframes", "keys": keys, "interpolation": "linear"}, n=9))
    assert _m(lin.frames[2].camera.to_world)[:3, 3] == pytest.approx((pos[0] + pos[4]) / 2)


def test_keyframed_object_rotation():
    keys = [{"frame": 0, "position": [0, 0, 0], "yaw": 0}, {"frame": 4, "position": [0, 0, 0], "yaw": 90}]
    seq = sequence_from_trajectory(_spec({"type": "static", "position": [0, 2, 6]},
                                         {"type": "keyframes", "keys": keys}))
    assert _m(seq.frames[-1].object_to_world)[:3, 2] == pytest.approx([1, 0, 0], abs=1e-9)
    assert _m(seq.frames[2].object_to_world)[:3, 2] == pytest.approx([np.sin(np.pi / 4), 0, np.cos(np.pi / 4)])


@pytest.mark.parametrize("mutate, message", [
    (lambda s: s["camera"].__setitem__("fov", 0), "camera.fov"),
    (lambda s: s["camera"]["path"].__setitem__("type", "spiral"), "camera.path.type"),
    (lambda s: s["camera"]["path"].__setitem__("position", [0, float("nan"), 1]), "camera.path.position[1]"),
    (lambda s: s["object"]["asset"].pop("mesh"), "object.asset.mesh"),
    (lambda s: s.__setitem__("frames", 0), "frames"),
    (lambda s: s["camera"]["path"].__setitem__("position", [0, 0.5, 0]), "camera.look_at (frame 0)"),
])
def test_bad_trajectory_fields_are_named(mutate, message):
    s = _spec({"type": "static", "position": [0, 2, 6]})
    mutate(s)
    with pytest.raises(SpecError) as err:
        sequence_from_trajectory(s)
    assert str(err.value).startswith(message), str(err.value)


def test_yaml_errors_name_the_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("frames: [1, 2\n")
    with pytest.raises(SpecError, match=r"bad.yaml: not valid YAML at line"):
        sequence_from_file(p)
    p.write_text(yaml.safe_dump(_spec({"type": "orbit", "radius": -1})))
    with pytest.raises(SpecError, match=r"bad.yaml: camera.path.radius: must be > 0"):
        sequence_from_file(p)
