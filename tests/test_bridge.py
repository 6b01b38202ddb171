"""Unreal ↔ canonical bridge: rotations, pose conversions, camera optics.

The conversions are checked three ways: algebraic properties (hypothesis),
closed forms (pitch ±90°, elementary rotations), and an end-to-end render in
which Mitsuba itself draws a point that Unreal's own projection places at a
known pixel (run in a subprocess so that no Mitsuba variant leaks into other
tests).
"""
from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from undream.bridge.unreal import (
    canonical_to_ue_camera,
    canonical_to_ue_object,
    matrix_to_ue_rotator,
    ue_camera_optics,
    ue_rotator_matrix,
    ue_to_canonical_camera,
    ue_to_canonical_object,
    ue_transform,
)
from undream.errors import BridgeError
from undream.spec import Camera, Transform

ROOT = Path(__file__).resolve().parents[1]
P = np.array([[1.0, 0, 0], [0, 0, 1], [0, 1, 0]])

angle = st.floats(-720.0, 720.0, allow_nan=False)
special = st.sampled_from([-180.0, -90.0, 0.0, 90.0, 180.0])
pitch = st.one_of(st.floats(-90.0, 90.0), special.filter(lambda a: abs(a) <= 90))
coord = st.floats(-1e5, 1e5, allow_nan=False)
scale_factor = st.one_of(st.floats(0.05, 20.0), st.floats(-20.0, -0.05))
vec3 = st.tuples(coord, coord, coord)


def canon_point(p_ue: np.ndarray) -> np.ndarray:
    """An Unreal point (cm) in canonical metres, written out independently of the bridge."""
    return np.array([p_ue[0], p_ue[2], p_ue[1]]) / 100.0


def is_rotation(r: np.ndarray, tol: float = 1e-9) -> bool:
    return np.allclose(r.T @ r, np.eye(3), atol=tol) and abs(np.linalg.det(r) - 1.0) < tol


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# --- rotators ---------------------------------------------------------------------

@given(angle, angle, angle)
def test_rotator_matrix_is_a_rotation(roll, pitch_, yaw):
    assert is_rotation(ue_rotator_matrix(roll, pitch_, yaw))


@given(angle, angle, angle)
def test_rotator_is_yaw_then_pitch_then_roll(roll, pitch_, yaw):
    # FRotator: yaw about Z, pitch (nose up) about -Y, roll about X, applied roll first.
    expected = rot_z(yaw) @ rot_y(-pitch_) @ rot_x(-roll)
    np.testing.assert_allclose(ue_rotator_matrix(roll, pitch_, yaw), expected, atol=1e-12)


def test_rotator_known_axes():
    np.testing.assert_array_equal(ue_rotator_matrix(0, 0, 90)[:, 0], [0, 1, 0])  # yaw turns X to Y
    np.testing.assert_array_equal(ue_rotator_matrix(0, 90, 0)[:, 0], [0, 0, 1])  # pitch raises X
    np.testing.assert_array_equal(ue_rotator_matrix(90, 0, 0)[:, 1], [0, 0, -1])  # roll right: Y dips


@given(angle, pitch, angle)
def test_matrix_to_rotator_round_trip(roll, pitch_, yaw):
    r = ue_rotator_matrix(roll, pitch_, yaw)
    back = matrix_to_ue_rotator(r)
    assert all(-180.0 <= a <= 180.0 for a in back)
    np.testing.assert_allclose(ue_rotator_matrix(*back), r, atol=1e-9)


@given(angle, st.sampled_from([-90.0, 90.0]), angle)
def test_matrix_to_rotator_at_gimbal_lock(roll, pitch_, yaw):
    r = ue_rotator_matrix(roll, pitch_, yaw)
    back_roll, back_pitch, back_yaw = matrix_to_ue_rotator(r)
    assert (back_pitch, back_yaw) == (pitch_, 0.0)
    np.testing.assert_allclose(ue_rotator_matrix(back_roll, back_pitch, back_yaw), r, atol=1e-12)


@given(angle, angle, st.sampled_from([-1.0, 1.0]))
def test_pitch_90_is_exact(roll, yaw, sign):
    r = ue_rotator_matrix(roll, 90.0 * sign, yaw)
    np.testing.assert_array_equal(r[:, 0], [0.0, 0.0, sign])  # forward exactly ±Z
    d = math.radians(roll - sign * yaw)  # only roll ∓ yaw matters at gimbal lock
    np.testing.assert_allclose(r[:, 1], [sign * math.sin(d), math.cos(d), 0.0], atol=1e-12)
    np.testing.assert_allclose(r[:, 2], [-sign * math.cos(d), math.sin(d), 0.0], atol=1e-12)
    cam = ue_to_canonical_camera(ue_transform([10, 20, 30], [roll, 90.0 * sign, yaw]))
    np.testing.assert_array_equal(cam[:3, 2], [0.0, sign, 0.0])  # Mitsuba forward exactly ±up
    Camera(Transform.from_rows(cam), 60.0, (8, 8))  # rigid enough for the spec


# --- transforms -------------------------------------------------------------------

@given(vec3, st.tuples(angle, angle, angle), st.tuples(scale_factor, scale_factor, scale_factor))
def test_ue_transform_is_t_r_s(location, rpy, scale):
    t, r, s = np.eye(4), np.eye(4), np.eye(4)
    t[:3, 3] = location
    r[:3, :3] = rot_z(rpy[2]) @ rot_y(-rpy[1]) @ rot_x(-rpy[0])
    s[:3, :3] = np.diag(scale)
    np.testing.assert_allclose(ue_transform(location, rpy, scale), t @ r @ s, rtol=1e-12, atol=1e-9)


@given(vec3, st.tuples(angle, angle, angle), st.tuples(scale_factor, scale_factor, scale_factor), vec3)
def test_object_conversion(location, rpy, scale, p_local_c):
    m_ue = ue_transform(location, rpy, scale)
    m_c = ue_to_canonical_object(m_ue)
    np.testing.assert_allclose(canonical_to_ue_object(m_c), m_ue, rtol=1e-12, atol=1e-9)
    # a canonical mesh point lands where Unreal puts the same point of the asset
    p_local_ue = np.array([p_local_c[0], p_local_c[2], p_local_c[1]]) * 100.0
    world_c = m_c @ np.append(p_local_c, 1.0)
    world_ue = m_ue @ np.append(p_local_ue, 1.0)
    np.testing.assert_allclose(world_c[:3], canon_point(world_ue[:3]), rtol=1e-9, atol=1e-6)
    rigid = ue_to_canonical_object(ue_transform(location, rpy))
    assert is_rotation(rigid[:3, :3])


@given(vec3, st.tuples(angle, pitch, angle), st.tuples(*[st.floats(0.05, 20.0)] * 3))
def test_camera_conversion_round_trip(location, rpy, scale):
    m_c = ue_to_canonical_camera(ue_transform(location, rpy, scale))
    assert is_rotation(m_c[:3, :3])
    assert Transform.from_rows(m_c).is_rigid()
    np.testing.assert_allclose(canonical_to_ue_camera(m_c), ue_transform(location, rpy), atol=1e-9)
    np.testing.assert_allclose(ue_to_canonical_camera(canonical_to_ue_camera(m_c)), m_c, atol=1e-12)


@settings(max_examples=300)
@given(vec3, vec3, angle)
def test_camera_looking_at_a_point_still_does(location, target, roll):
    d = np.subtract(target, location)
    if np.linalg.norm(d) < 1.0:
        return
    yaw = math.degrees(math.atan2(d[1], d[0]))
    pitch_ = math.degrees(math.atan2(d[2], math.hypot(d[0], d[1])))
    r_ue = ue_rotator_matrix(roll, pitch_, yaw)
    m = ue_to_canonical_camera(ue_transform(location, (roll, pitch_, yaw)))
    to_target = canon_point(np.asarray(target)) - m[:3, 3]
    np.testing.assert_allclose(m[:3, 3], canon_point(np.asarray(location)), atol=1e-12)
    np.testing.assert_allclose(m[:3, 2], to_target / np.linalg.norm(to_target), atol=1e-9)
    np.testing.assert_allclose(m[:3, 1], P @ r_ue[:, 2], atol=1e-12)  # up stays up
    np.testing.assert_allclose(-m[:3, 0], P @ r_ue[:, 1], atol=1e-12)  # Unreal's right is -left
    local = np.linalg.solve(m, np.append(canon_point(np.asarray(target)), 1.0))
    assert local[2] > 0  # in front of the camera
    np.testing.assert_allclose(local[:2], 0.0, atol=1e-9 * max(1.0, local[2]))


# --- optics -----------------------------------------------------------------------

def test_optics_known_answers():
    assert ue_camera_optics(60.0, 16 / 9, (64, 36)) == (60.0, (64, 36), None)
    assert ue_camera_optics(60.0, 1.5, (64, 36)) == (60.0, (64, 36), (64, 42))  # 42.67 → 42: even margin
    assert ue_camera_optics(60.0, 1.5, (36, 36)) == (60.0, (36, 36), (54, 36))  # height fills
    fov, res, film = ue_camera_optics(60.0, 1.5, (35, 36))  # 54 px of filmback → 55 (odd image width)
    assert (res, film) == ((35, 36), (55, 36))
    assert fov == pytest.approx(math.degrees(2 * math.atan(math.tan(math.radians(30)) * 55 / 54)))


@given(st.floats(1.0, 170.0), st.floats(0.3, 4.0), st.integers(1, 4000), st.integers(1, 4000))
def test_optics_is_an_exact_centred_crop(fov, aspect, w, h):
    fov_c, res, film = ue_camera_optics(fov, aspect, (w, h))
    assert res == (w, h)
    fw, fh = film or res
    assert fw >= w and fh >= h and (fw - w) % 2 == 0 and (fh - h) % 2 == 0
    tan_c = math.tan(math.radians(fov_c) / 2)
    if w / h >= aspect:  # the width fills: fov and pixel pitch as in Unreal
        assert fov_c == fov and fw == w and abs(fh - w / aspect) <= 1.0
        assert (film is None) == (w / aspect - h < 1.0)
    else:  # the height fills: same pixel pitch as Unreal's filmback
        assert abs(fw - h * aspect) <= 1.0 and fh == h
        assert tan_c / fw == pytest.approx(math.tan(math.radians(fov) / 2) / (h * aspect), rel=1e-12)
        assert (film is None) == (h * aspect - w < 1.0)
    Camera(Transform.identity(), fov_c, res, film)  # the spec accepts it


# --- bad input --------------------------------------------------------------------

@pytest.mark.parametrize("call, message", [
    (lambda: ue_transform([0, 0, 0], [0, float("nan"), 0]), "rotation_rpy_deg[1]: must be finite, got nan"),
    (lambda: ue_transform([0, float("inf"), 0], [0, 0, 0]), "location_cm[1]: must be finite, got inf"),
    (lambda: ue_transform([0, 0, 0], [0, 0, 0], [1, 1, 0]), "scale[2]: must be non-zero, got 0.0"),
    (lambda: ue_transform([0, 0], [0, 0, 0]), "location_cm: must have shape (3,)"),
    (lambda: ue_transform("abc", [0, 0, 0]), "location_cm: must be numbers"),
    (lambda: ue_rotator_matrix(0, float("nan"), 0), "rotation_rpy_deg[1]: must be finite"),
    (lambda: ue_to_canonical_object(np.zeros((4, 4))), "M[3]: must be [0, 0, 0, 1]"),
    (lambda: ue_to_canonical_object(np.diag([1, 1, 0, 1])), "M: must have an invertible 3×3 part"),
    (lambda: ue_to_canonical_object(np.eye(3)), "M: must have shape (4, 4)"),
    (lambda: ue_to_canonical_camera(np.diag([1.0, -1.0, 1.0, 1.0])), "must not mirror"),
    (lambda: ue_to_canonical_camera([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "no shear"),
    (lambda: canonical_to_ue_camera(np.diag([2.0, 2.0, 2.0, 1.0])), "M[:3, :3]: must be a rotation"),
    (lambda: matrix_to_ue_rotator(np.diag([1.0, 1.0, -1.0])), "R: must be a rotation"),
    (lambda: ue_camera_optics(0.0, 1.5, (64, 36)), "fov_h_deg: must be in (0, 180)"),
    (lambda: ue_camera_optics(60.0, float("nan"), (64, 36)), "filmback_aspect: must be finite"),
    (lambda: ue_camera_optics(60.0, -1.0, (64, 36)), "filmback_aspect: must be > 0"),
    (lambda: ue_camera_optics(60.0, 1.5, (64, 0)), "resolution_wh: must be two integers"),
    (lambda: ue_camera_optics(60.0, 1.5, (64.5, 36)), "resolution_wh: must be two integers"),
])
def test_bad_input_names_the_value(call, message):
    with pytest.raises(BridgeError) as err:
        call()
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_bridge_does_not_import_mitsuba():
    code = "import sys, undream.bridge.unreal; sys.exit('mitsuba' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0


# --- end to end: Unreal's projection vs Mitsuba's render ------------------------------

RENDER = r"""
import json, sys
import mitsuba as mi
import numpy as np
mi.set_variant("scalar_rgb")
out = []
for case in json.load(sys.stdin):
    film = {"type": "hdrfilm", "width": case["film"][0], "height": case["film"][1],
            "rfilter": {"type": "box"}, "pixel_format": "luminance"}
    w, h = case["resolution"]
    film.update(crop_offset_x=(case["film"][0] - w) // 2, crop_offset_y=(case["film"][1] - h) // 2,
                crop_width=w, crop_height=h)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": case["fov"], "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f(case["to_world"]), "film": film,
                   "sampler": {"type": "independent", "sample_count": 256}},
        "ball": {"type": "sphere", "center": case["center"], "radius": case["radius"],
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    img = np.array(mi.render(scene))[..., 0]
    ys, xs = np.mgrid[:h, :w] + 0.5
    out.append([float((xs * img).sum() / img.sum()), float((ys * img).sum() / img.sum())])
print(json.dumps(out))
"""

CASES = [  # location cm, rotation (roll, pitch, yaw), fov, filmback mm, resolution, target pixels
    ((120, -340, 210), (0, -10, 35), 60.0, (36, 24), (64, 36), [(16.0, 9.0), (48.5, 27.0), (40.0, 12.5)]),
    ((0, 0, 500), (25, 40, -120), 45.0, (36, 24), (36, 36), [(8.0, 8.0), (27.0, 20.0)]),
    ((50, 60, 900), (0, -90, 70), 50.0, (36, 20.25), (64, 36), [(12.0, 6.0), (50.0, 30.0)]),
    ((-300, 10, 40), (-30, 90, 10), 70.0, (36, 24), (35, 36), [(6.0, 30.0), (28.0, 4.0)]),
]


def ue_pixel_ray(rpy, fov, filmback, resolution, pixel) -> np.ndarray:
    """Unit world ray (Unreal axes) through ``pixel`` of the centre-cropped filmback image."""
    w, h = resolution
    aspect = filmback[0] / filmback[1]
    px_per_unit = w / 2 if w / h >= aspect else h * aspect / 2  # pixels per tan-plane unit / tan(fov/2)
    t = math.tan(math.radians(fov) / 2)
    right, up = (pixel[0] - w / 2) / px_per_unit * t, (h / 2 - pixel[1]) / px_per_unit * t
    d = ue_rotator_matrix(*rpy) @ np.array([1.0, right, up])  # local: +X forward, +Y right, +Z up
    return d / np.linalg.norm(d)


@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="mitsuba not installed")
def test_mitsuba_renders_points_where_unreal_projects_them():
    cases, expected = [], []
    for location, rpy, fov, filmback, res, pixels in CASES:
        fov_c, res_c, film = ue_camera_optics(fov, filmback[0] / filmback[1], res)
        to_world = ue_to_canonical_camera(ue_transform(location, rpy)).tolist()
        w, h = res
        px_size = math.tan(math.radians(fov) / 2) / (w / 2 if w / h >= filmback[0] / filmback[1]
                                                      else h * filmback[0] / filmback[1] / 2)
        for pixel in pixels:
            dist = 700.0  # cm
            point = np.asarray(location) + dist * ue_pixel_ray(rpy, fov, filmback, res, pixel)
            radius = 1.2 * px_size * dist / 100.0  # about 1.2 px, in metres
            cases.append({"to_world": to_world, "fov": fov_c, "resolution": list(res_c),
                          "film": list(film or res_c), "center": canon_point(point).tolist(),
                          "radius": radius})
            expected.append(pixel)
    run = subprocess.run([sys.executable, "-c", RENDER], input=json.dumps(cases), capture_output=True,
                         text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    got = np.array(json.loads(run.stdout))
    np.testing.assert_allclose(got, np.array(expected), atol=0.15)
