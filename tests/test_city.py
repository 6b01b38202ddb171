"""``background: city``: the spec accepts it; its seeded props never touch the object, an actor, a
camera or a line of sight on any example's paths; Mitsuba and Cycles render a city frame with the
object where the independent projection puts it.

Cycles tests skip without Blender's Python (fail where ``UNDREAM_REQUIRE_SERVICES`` is set), as in
tests/test_sim_blender.py.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from projection import centroid, load, visible_mask
from undream.errors import SpecError
from undream.scene.background import Prop, props
from undream.spec import BACKGROUNDS, Environment, Sequence

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.yaml"))
UNIT_CORNERS = {  # each Mitsuba primitive's local bounding box: (min, max)
    "cube": ((-1, -1, -1), (1, 1, 1)), "sphere": ((-1, -1, -1), (1, 1, 1)),
    "cylinder": ((-1, -1, 0), (1, 1, 1)), "rectangle": ((-1, -1, 0), (1, 1, 0)),
}


def test_spec_accepts_city_and_names_the_valid_backgrounds():
    assert "city" in BACKGROUNDS and Environment(background="city").background == "city"
    with pytest.raises(SpecError) as err:
        Environment.from_json({"background": "downtown"})
    msg = str(err.value)
    assert "\n" not in msg and "downtown" in msg and "plain, park, street, city" in msg


def _city(seq: Sequence) -> Sequence:
    return dataclasses.replace(seq, frames=tuple(
        dataclasses.replace(f, environment=dataclasses.replace(f.environment, background="city"))
        for f in seq.frames))


def _dolly_camera() -> Sequence:
    """A camera dollying past a static bin (no example has a ``dolly`` camera)."""
    from undream.scene.trajectory import sequence_from_trajectory

    return sequence_from_trajectory({
        "frames": 6, "camera": {"fov": 40, "resolution": [32, 32],
                                "path": {"type": "dolly", "start": [-4, 1.5, 5], "end": [4, 2.5, 3]}},
        "object": {"asset": {"name": "bin", "mesh": "builtin:trash_bin"}, "path": {"type": "static",
                                                                                   "position": [1, 0, -2]}},
        "environment": {"background": "city"}})


def _sequences() -> dict[str, Sequence]:
    from undream.scene.sources import sequence_from_file
    from undream.settings import load_local

    cache = load_local().undream_cache  # the asset:NAME examples (car, person)
    out = {p.stem: _city(sequence_from_file(p, cache)) for p in EXAMPLES}
    out["dolly_camera"] = _dolly_camera()
    return out


def _box_of(p: Prop) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = (np.array(v, float) for v in UNIT_CORNERS[p.shape])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    world = (p.to_world @ np.c_[corners, np.ones(8)].T).T[:, :3]
    return world.min(axis=0), world.max(axis=0)


def _mesh_box(asset, base_dir: Path, index: int, to_world) -> tuple[np.ndarray, np.ndarray]:
    from undream.scene.builtin import asset_mesh

    v = asset_mesh(asset, base_dir, index if asset.per_frame else None).vertices
    m = np.array(to_world.matrix)
    w = (m @ np.c_[v, np.ones(len(v))].T).T[:, :3]
    return w.min(axis=0), w.max(axis=0)


def _overlap(a, b, pad: float = 0.0) -> bool:
    return bool(np.all(a[0] - pad < b[1]) and np.all(b[0] - pad < a[1]))


def _segment_hits(p0: np.ndarray, p1: np.ndarray, box) -> bool:
    """Whether the segment p0 → p1 passes through the axis-aligned box (slab test)."""
    d = p1 - p0
    t0, t1 = 0.0, 1.0
    for k in range(3):
        if abs(d[k]) < 1e-12:
            if not box[0][k] <= p0[k] <= box[1][k]:
                return False
            continue
        a, b = sorted(((box[0][k] - p0[k]) / d[k], (box[1][k] - p0[k]) / d[k]))
        t0, t1 = max(t0, a), min(t1, b)
        if t0 > t1:
            return False
    return True


@pytest.mark.parametrize("name", [p.stem for p in EXAMPLES] + ["dolly_camera"])
def test_city_props_keep_clear_of_object_actors_cameras_and_sight_lines(name):
    """On every example's paths (and a dolly camera): no prop's box meets the object's or an actor's box
    in any frame, holds a camera, or crosses the segment from a camera to the object's centre."""
    seq = _sequences()[name]
    out = props(seq, "city")
    assert len(out) >= 30, f"{name}: only {len(out)} city props survive"
    boxes = [_box_of(p) for p in out]
    actors = {a.name: a for a in seq.actors}
    cams = [np.array(f.camera.to_world.translation) for f in seq.frames]
    for c0, c1 in zip(cams, cams[1:]):  # the camera's path between frames, too
        assert not any(_segment_hits(c0, c1, box) for box in boxes), f"{name}: a prop stands on the camera's path"
    for f in seq.frames:
        obj = _mesh_box(seq.asset, ROOT / "examples", f.index, f.object_to_world)
        cam = np.array(f.camera.to_world.translation)
        centre = (obj[0] + obj[1]) / 2
        occupied = [obj] + [_mesh_box(actors[a.name], ROOT / "examples", f.index, a.to_world) for a in f.actors]
        for p, box in zip(out, boxes):
            for occ in occupied:
                assert not _overlap(box, occ, pad=0.1), f"{name} frame {f.index}: a {p.shape} meets the object/actor"
            assert not _overlap(box, (cam, cam), pad=0.3), f"{name} frame {f.index}: a {p.shape} holds the camera"
            assert not _segment_hits(cam, centre, box), f"{name} frame {f.index}: a {p.shape} hides the object"


def test_city_is_seeded():
    seq = _dolly_camera()
    a, b = props(seq, "city"), props(seq, "city")
    other = props(dataclasses.replace(seq, seed=7), "city")
    assert [p.shape for p in a] == [p.shape for p in b]
    assert all(np.array_equal(p.to_world, q.to_world) and p.colour == q.colour for p, q in zip(a, b))
    assert len(other) != len(a) or not all(np.array_equal(p.to_world, q.to_world) for p, q in zip(a, other))


# --- rendering -----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def city_scene(tmp_path_factory, mi):
    """Three 32 px frames of a bin in the city, the camera passing along the road."""
    from undream.scene.trajectory import sequence_from_trajectory
    from undream.scenedir.init import InitOptions, init_scene

    seq = sequence_from_trajectory({
        "name": "city", "seed": 3, "frames": 3,
        "camera": {"fov": 45, "resolution": [32, 32], "path": {"type": "dolly", "start": [-2.5, 1.4, 3.2],
                                                               "end": [2.5, 1.8, 3.0]},
                   "look_at": "object", "look_at_offset": [0, 0.5, 0]},
        "object": {"asset": {"name": "bin", "mesh": "builtin:trash_bin", "texture": {"resolution": [16, 16]}},
                   "path": {"type": "static", "position": [0, 0, 0]}, "yaw": 20},
        "environment": {"weather": "clear", "time_of_day": 15.0, "background": "city"}})
    return init_scene(seq, tmp_path_factory.mktemp("city") / "scene", InitOptions(verify_spp=16))


def test_mitsuba_renders_the_city_and_the_object_where_the_projection_puts_it(city_scene):
    from undream.scenedir.verify import read_mask

    xml = (city_scene / "frames" / "sim_0000.xml").read_text()
    assert xml.count('type="cube"') >= 20 and 'type="cylinder"' in xml and 'type="rectangle"' in xml
    seq = load(city_scene)
    for f in seq["frames"]:
        mask, expect = read_mask(city_scene, f["index"]), visible_mask(city_scene, f, seq)
        assert expect.sum() >= 12
        err = float(np.linalg.norm(centroid(mask) - centroid(expect)))
        assert err <= 1.5, f"frame {f['index']}: Mitsuba's mask centroid off by {err:.2f} px"



def test_cycles_renders_the_city_and_agrees_with_mitsuba(cycles, city_scene):
    """Cycles' coverage mask of each frame: IoU ≥ 0.9 with Mitsuba's, centroid within 1.5 px of the
    independent projection; the frames' mean radiance Cycles / Mitsuba within 5 %."""
    from undream.scenedir.verify import read_mask
    from undream.sim import make_backend

    seq = load(city_scene)
    tex = np.full((16, 16, 3), 0.5, np.float32)
    mit = make_backend("mitsuba", city_scene)
    sim = make_backend("blender", city_scene, threads=2)
    try:
        for f in seq["frames"]:
            i = f["index"]
            mask, mitsuba = sim.coverage(i, spp=64) > 0.5, read_mask(city_scene, i)
            iou = (mask & mitsuba).sum() / (mask | mitsuba).sum()
            err = float(np.linalg.norm(centroid(mask) - centroid(visible_mask(city_scene, f, seq))))
            a, b = mit.render(i, tex, 64, 4).mean(), sim.render(i, tex, 64, 4).mean()
            print(f"frame {i}: IoU {iou:.3f}, centroid {err:.2f} px, Cycles / Mitsuba mean radiance {b / a:.3f}")
            assert iou >= 0.9 and err <= 1.5
            assert abs(b / a - 1) < 0.05, f"frame {i}: Cycles / Mitsuba = {b / a:.3f}"
    finally:
        sim.close()


def test_props_are_placed_once_per_sequence_and_background(monkeypatch):
    """Every frame's scene files ask for the props; each placement checks every frame's sight line,
    so placing them per frame made a multi-condition init quadratic in its frames."""
    from undream.scene import background
    from undream.scene.mitsuba_scene import ScenePaths, scene_dict
    from undream.scene.sources import sequence_from_file

    placed, place = [], background._place
    monkeypatch.setattr(background, "_place", lambda seq, bg: placed.append(bg) or place(seq, bg))
    seq = sequence_from_file(ROOT / "examples" / "bin_orbit.yaml")
    for s in (seq, _city(seq)):
        first = None
        for f in s.frames:
            for kind in ("sim", "mask"):
                d = scene_dict(s, f, ScenePaths(".."), kind)
                shown = [(v["type"], v["to_world"].m) for k, v in d.items()
                         if k.startswith("prop_")]
                first = shown if first is None else first
                assert shown == first and shown, "every frame shows the same props"
    assert placed == [seq.frames[0].environment.background, "city"]
