"""Unreal Engine ↔ canonical (Mitsuba) coordinates: poses as matrices, camera optics.

Unreal: left-handed, Z up, centimetres. An actor's local +X is forward, +Y
right, +Z up; a camera looks along its local +X with +Z up and +Y to the
image's right. Rotations are ``FRotator`` roll/pitch/yaw in degrees (the
order of ``unreal.Rotator(roll, pitch, yaw)`` in Unreal's Python).

Canonical (undream, Mitsuba): right-handed, Y up, metres. A camera looks along
its local +Z with +Y up and local +X to the image's *left*.

All matrices are 4×4 (or 3×3) numpy arrays in column-vector convention
(``p_world = M @ p_local``); Unreal's own ``FMatrix`` is row-vector, so the
columns here are its rows. The basis change is ``P`` (canonical x = UE x,
canonical y = UE z, canonical z = UE y; det −1 flips handedness) with
1 m = 100 cm:

- objects: ``M_c = C · M_ue · C⁻¹`` with ``C = [[P / 100, 0], [0, 1]]``;
  undream meshes are authored in canonical local metres, which ``C⁻¹`` maps
  to Unreal local centimetres (canonical (x, y, z) m ↔ UE (100x, 100z, 100y) cm,
  so an asset's front, canonical +Z, is the actor's local +Y);
- cameras: ``M_c = C · M_ue · C⁻¹ · K`` where ``K`` takes Mitsuba camera axes
  to the canonicalised Unreal camera axes (forward +Z → P·X_ue, up +Y → P·Z_ue,
  left +X → −P·Y_ue); camera scale is stripped.

Poses are composed as matrices and never pass through Euler angles on the way
in, so pitch ±90° is exact. Pure numpy; Mitsuba is not imported.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from undream.errors import BridgeError

CM_PER_M = 100.0
_P = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
# Columns: images of Mitsuba camera +X (left), +Y (up), +Z (forward) in the
# canonicalised Unreal camera frame (P applied to UE's local X, Y, Z).
_K = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
_ROT_TOL = 1e-6
_GIMBAL_TOL = 1e-12


def _array(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite entries, else BridgeError."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise BridgeError(f"{name}: must be numbers of shape {shape}, got {value!r}") from None
    if a.shape != shape:
        raise BridgeError(f"{name}: must have shape {shape}, got shape {a.shape}")
    finite = np.isfinite(a)
    if not finite.all():
        idx = tuple(int(i) for i in np.unravel_index(int(np.argmin(finite)), a.shape))
        where = "".join(f"[{i}]" for i in idx)
        raise BridgeError(f"{name}{where}: must be finite, got {float(a[idx])}")
    return a


def _affine(name: str, m: Any) -> np.ndarray:
    a = _array(name, m, (4, 4))
    if not np.array_equal(a[3], [0.0, 0.0, 0.0, 1.0]):
        raise BridgeError(f"{name}[3]: must be [0, 0, 0, 1] (affine transform), got {a[3].tolist()}")
    if abs(np.linalg.det(a[:3, :3])) < 1e-12:
        raise BridgeError(f"{name}: must have an invertible 3×3 part, got {a[:3, :3].tolist()}")
    return a


def _rotation(name: str, r: Any) -> np.ndarray:
    a = _array(name, r, (3, 3))
    if not np.allclose(a.T @ a, np.eye(3), atol=_ROT_TOL) or np.linalg.det(a) <= 0:
        raise BridgeError(f"{name}: must be a rotation (orthonormal, determinant +1), "
                          f"got {a.tolist()}")
    return a


def _compose(linear: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = translation
    return m


def _sincos_deg(angle: float) -> tuple[float, float]:
    """sin and cos of ``angle`` degrees, exact at multiples of 90°."""
    quarter = round(math.fmod(angle, 360.0) / 90.0)
    rest = math.radians(math.fmod(angle, 360.0) - 90.0 * quarter)
    s, c = math.sin(rest), math.cos(rest)
    for _ in range(quarter % 4):
        s, c = c, -s
    return s, c


def ue_rotator_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The (3, 3) rotation of an Unreal ``FRotator`` (degrees), column-vector convention.

    Columns are the world (Unreal, Z up) images of the local X (forward),
    Y (right) and Z (up) axes, i.e. the rows of Unreal's ``FRotationMatrix``.
    Exact (no rounding noise) at multiples of 90°.
    """
    v = _array("rotation_rpy_deg", [roll, pitch, yaw], (3,))
    sr, cr = _sincos_deg(v[0])
    sp, cp = _sincos_deg(v[1])
    sy, cy = _sincos_deg(v[2])
    x = (cp * cy, cp * sy, sp)
    y = (sr * sp * cy - cr * sy, sr * sp * sy + cr * cy, -sr * cp)
    z = (-(cr * sp * cy + sr * sy), cy * sr - cr * sp * sy, cr * cp)
    return np.array([x, y, z]).T


def matrix_to_ue_rotator(r: Any) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in degrees of a (3, 3) rotation in Unreal world axes.

    Inverse of :func:`ue_rotator_matrix` (as ``FMatrix::Rotator`` does it),
    with angles in [−180°, 180°]. At gimbal lock (pitch ±90°) yaw is set to 0
    and roll carries the remaining turn. For display and round trips only:
    the forward conversions never go through Euler angles.
    """
    a = _rotation("R", r)
    x, y, z = a[:, 0], a[:, 1], a[:, 2]
    horizontal = math.hypot(x[0], x[1])
    if horizontal <= _GIMBAL_TOL:
        pitch, yaw = math.copysign(90.0, x[2]), 0.0
    else:
        pitch, yaw = math.degrees(math.atan2(x[2], horizontal)), math.degrees(math.atan2(x[1], x[0]))
    sy, cy = _sincos_deg(yaw)
    right0 = np.array([-sy, cy, 0.0])  # local Y of the same rotator with roll 0
    roll = math.degrees(math.atan2(float(z @ right0), float(y @ right0)))
    return roll, pitch, yaw


def ue_transform(location_cm: Any, rotation_rpy_deg: Any, scale: Any = (1.0, 1.0, 1.0)) -> np.ndarray:
    """An Unreal actor transform as a (4, 4) matrix ``T · R · S`` (Unreal axes, cm).

    ``location_cm`` (x, y, z) centimetres; ``rotation_rpy_deg`` (roll, pitch,
    yaw) degrees; ``scale`` (x, y, z) factors, non-zero (negative mirrors).
    Scale applies first, in the actor's local axes.
    """
    t = _array("location_cm", location_cm, (3,))
    rpy = _array("rotation_rpy_deg", rotation_rpy_deg, (3,))
    s = _array("scale", scale, (3,))
    for i, v in enumerate(s):
        if v == 0:
            raise BridgeError(f"scale[{i}]: must be non-zero, got {float(v)}")
    return _compose(ue_rotator_matrix(*rpy) * s, t)


def ue_to_canonical_object(m: Any) -> np.ndarray:
    """An Unreal object transform (4×4, cm) as a canonical one (4×4, metres).

    ``C · M · C⁻¹``: the linear part (rotation and scale) becomes ``P L P``,
    the translation ``P t / 100``.
    """
    a = _affine("M", m)
    return _compose(_P @ a[:3, :3] @ _P, _P @ a[:3, 3] / CM_PER_M)


def canonical_to_ue_object(m: Any) -> np.ndarray:
    """Inverse of :func:`ue_to_canonical_object`: canonical (metres) → Unreal (cm)."""
    a = _affine("M", m)
    return _compose(_P @ a[:3, :3] @ _P, _P @ a[:3, 3] * CM_PER_M)


def _strip_scale(linear: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(linear, axis=0)
    r = linear / norms
    if not np.allclose(r.T @ r, np.eye(3), atol=_ROT_TOL):
        raise BridgeError(f"M: a camera transform must be rotation × axis scale (no shear), "
                          f"got {linear.tolist()}")
    if np.linalg.det(r) <= 0:
        raise BridgeError(f"M: a camera transform must not mirror (negative scale), "
                          f"got {linear.tolist()}")
    return r


def ue_to_canonical_camera(m: Any) -> np.ndarray:
    """An Unreal camera transform (4×4, cm; looks along +X, +Z up) as a Mitsuba camera's.

    Returns a rigid (4, 4) canonical ``to_world`` (metres) whose local +Z is
    the camera's forward, +Y its up and +X the image's left. Any scale in
    ``m`` is stripped (cameras are rigid).
    """
    a = _affine("M", m)
    r = _strip_scale(a[:3, :3])
    return _compose(_P @ r @ _P @ _K, _P @ a[:3, 3] / CM_PER_M)


def canonical_to_ue_camera(m: Any) -> np.ndarray:
    """Inverse of :func:`ue_to_canonical_camera`: a rigid Mitsuba camera → Unreal (cm)."""
    a = _affine("M", m)
    r = _rotation("M[:3, :3]", a[:3, :3])
    return _compose(_P @ r @ _K.T @ _P, _P @ a[:3, 3] * CM_PER_M)


def _same_parity(exact: float, n: int) -> int:
    """The integer nearest to ``exact`` (≥ n) that differs from ``n`` by an even number."""
    return n + 2 * math.floor((exact - n) / 2.0 + 0.5)


def _optics_args(fov_h_deg: Any, filmback_aspect: Any, resolution_wh: Any) -> tuple[float, float, int, int]:
    fov, aspect = _array("fov_h_deg", fov_h_deg, ()), _array("filmback_aspect", filmback_aspect, ())
    if not 0 < fov < 180:
        raise BridgeError(f"fov_h_deg: must be in (0, 180) degrees, got {float(fov)}")
    if aspect <= 0:
        raise BridgeError(f"filmback_aspect: must be > 0 (width / height), got {float(aspect)}")
    res = list(resolution_wh) if isinstance(resolution_wh, (list, tuple)) else resolution_wh
    if (not isinstance(res, list) or len(res) != 2
            or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1 for v in res)):
        raise BridgeError(f"resolution_wh: must be two integers ≥ 1 (width, height), got {resolution_wh!r}")
    return float(fov), float(aspect), int(res[0]), int(res[1])


def ue_camera_optics(fov_h_deg: float, filmback_aspect: float,
                     resolution_wh: tuple[int, int]) -> tuple[float, tuple[int, int], tuple[int, int] | None]:
    """Mitsuba optics ``(fov_deg, resolution, film)`` of an Unreal cine camera.

    ``fov_h_deg``: Unreal's horizontal field of view over the filmback width,
    degrees. ``filmback_aspect``: sensor width / height. ``resolution_wh``:
    output (width, height) pixels. The output image is the largest centred
    crop of the filmback image with the output's aspect, scaled to the output
    resolution. The result fits :class:`undream.spec.Camera`: ``fov_deg`` is
    the horizontal fov over the ``film`` width, and the image is the centred
    ``resolution`` window of ``film`` (``None``: the film is the image).

    - Output at least as wide as the filmback: the width fills, ``film`` is
      ``(W, ≈W / aspect)`` and the fov is unchanged.
    - Narrower: the height fills, ``film`` is ``(≈H · aspect, H)``; the fov is
      unchanged when ``H · aspect`` is a whole number of pixels, otherwise it
      is rescaled by ``film_w / (H · aspect)`` so that the pixel pitch is
      exactly Unreal's.

    ``≈``: the film side is rounded to the nearest size whose difference from
    the image side is even, so that the crop is exactly centred (odd margins
    would shift the image by half a pixel); the film is ``None`` when the
    margin is under 1 px.
    """
    fov, aspect, w, h = _optics_args(fov_h_deg, filmback_aspect, resolution_wh)
    if w / h >= aspect:
        film = (w, _same_parity(w / aspect, h))
    else:
        exact_w = h * aspect
        film = (_same_parity(exact_w, w), h)
        if film[0] != exact_w:
            half = math.atan(math.tan(math.radians(fov) / 2.0) * film[0] / exact_w)
            fov = math.degrees(2.0 * half)
    return fov, (w, h), (None if film == (w, h) else film)
