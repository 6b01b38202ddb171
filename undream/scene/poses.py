"""Pose construction in the canonical frame (right-handed, Y up, metres).

All functions return 4×4 numpy arrays in column-vector convention.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from undream.errors import SpecError

WORLD_UP = np.array([0.0, 1.0, 0.0])


def look_at(origin, target, up=WORLD_UP, field: str = "camera", strict: bool = False) -> np.ndarray:
    """Mitsuba camera-to-world: local +Z towards ``target``, +Y up, +X to the image's left.

    When the view direction is parallel to ``up`` (looking straight down or
    up), -Z then +X are tried as the up hint, so the result is always rigid;
    ``strict`` (an ``up`` the user gave): SpecError instead.
    """
    o, t = np.asarray(origin, float), np.asarray(target, float)
    d = t - o
    n = np.linalg.norm(d)
    if not np.isfinite(n) or n < 1e-9:
        raise SpecError(f"{field}: camera position {o.tolist()} and look-at target {t.tolist()} coincide")
    d = d / n
    if strict and np.linalg.norm(np.cross(np.asarray(up, float), d)) <= 1e-6:
        raise SpecError(f"{field}: camera.up {np.asarray(up).tolist()} is parallel to the view direction "
                        f"{d.round(6).tolist()}; give an up that is not along the line of sight")
    for hint in (np.asarray(up, float), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])):
        left = np.cross(hint, d)
        if np.linalg.norm(left) > 1e-6:
            break
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def object_pose(position, rotation: Rotation, scale: float = 1.0) -> np.ndarray:
    """Object-to-world from a position (m), a rotation and a uniform scale."""
    m = np.eye(4)
    m[:3, :3] = rotation.as_matrix() * scale
    m[:3, 3] = np.asarray(position, float)
    return m


def yaw_rotation(yaw_deg: float) -> Rotation:
    """Rotation about +Y; yaw 0 keeps the object's front (+Z) along +Z."""
    return Rotation.from_rotvec([0.0, np.radians(yaw_deg), 0.0])


def heading_yaw(direction) -> float:
    """Yaw (degrees) that turns the object's front (+Z) along a horizontal direction."""
    d = np.asarray(direction, float)
    return float(np.degrees(np.arctan2(d[0], d[2])))
