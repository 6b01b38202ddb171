"""Motion: the built-in pedestrian, an actor that walks through the frame and hides the object in the
frames it crosses (in Mitsuba and in Cycles), and animated meshes as one file per frame.

The Cycles checks need Blender's Python (``.venv-blender``); without it they skip with the reason
(and fail where ``UNDREAM_REQUIRE_SERVICES`` is set).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from projection import load, visible_mask
from undream.errors import AssetError, SpecError
from undream.scene.builtin import builtin_mesh, pedestrian
from undream.scene.mesh import Mesh, read_ply, write_ply
from undream.scenedir.init import InitOptions, init_scene
from undream.scenedir.verify import read_mask
from undream.spec import Asset, load_sequence

ROOT = Path(__file__).resolve().parents[1]
CROSSING = ROOT / "examples" / "pedestrian_crossing.yaml"


# --- the pedestrian ---------------------------------------------------------------------------------

def test_pedestrian_stands_faces_front_and_walks():
    still, mid = builtin_mesh("pedestrian"), pedestrian(0.25)
    lo, hi = still.bounds()
    assert np.allclose([lo[1], hi[1]], [0.0, 1.76], atol=1e-5)  # on the ground, 1.76 m tall
    assert np.allclose([lo[0], hi[0]], [-0.31, 0.31], atol=1e-5) and hi[2] - lo[2] < 0.25
    assert still.uvs.min() >= 0 and still.uvs.max() <= 1
    assert mid.n_vertices == still.n_vertices and np.array_equal(mid.uvs, still.uvs)  # one UV layout
    lo_m, hi_m = mid.bounds()
    assert hi_m[2] - lo_m[2] > 0.6  # mid-stride: legs and arms swing along the walking direction (±Z)
    # Closed and outward: the signed volume (divergence theorem) is positive.
    p = still.vertices.astype(float)[still.faces]
    assert np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6 > 0.05


# --- a walker crossing in front of the object ---------------------------------------------------------

@pytest.fixture(scope="module")
def crossing(tmp_path_factory, mi):
    return init_scene(CROSSING, tmp_path_factory.mktemp("crossing") / "scene", InitOptions(verify_spp=4))


def _occlusion_check(counts: dict[int, int], scene: Path) -> None:
    """Frames the walker crosses (by the independent projection) lose object pixels; the others keep
    exactly the object's unoccluded count (static camera and object: the same in every clear frame)."""
    seq = load(scene)
    hidden = {f["index"]: int(visible_mask(scene, f, seq, actors=False).sum() - visible_mask(scene, f, seq).sum())
              for f in seq["frames"]}
    clear = [i for i, h in hidden.items() if h == 0]
    crossed = [i for i, h in hidden.items() if h >= 8]
    assert len(clear) >= 6 and len(crossed) >= 2, hidden
    reference = np.median([counts[i] for i in clear])
    for i in clear:
        assert abs(counts[i] - reference) <= 2, f"frame {i}: {counts[i]} object pixels, unoccluded {reference}"
    for i in crossed:
        assert counts[i] <= reference - 0.5 * hidden[i], \
            f"frame {i}: {counts[i]} object pixels, {reference} unoccluded, the walker hides {hidden[i]}"


def test_walker_hides_the_object_in_mitsuba(crossing):
    seq = load_sequence(crossing / "sequence.json")
    _occlusion_check({f.index: int(read_mask(crossing, f.index).sum()) for f in seq.frames}, crossing)


def test_walker_hides_the_object_in_cycles(cycles, crossing):
    from undream.sim import make_backend

    seq = load_sequence(crossing / "sequence.json")
    sim = make_backend("blender", crossing, threads=2)
    try:
        counts = {f.index: int((sim.coverage(f.index, spp=16) > 0.5).sum()) for f in seq.frames}
    finally:
        sim.close()
    _occlusion_check(counts, crossing)


def test_walker_uses_its_frame_s_mesh(crossing):
    """Frame k's scene file names meshes/walker_000k.ply, and that file is the example's walker_000k.ply."""
    seq = load_sequence(crossing / "sequence.json")
    assert seq.actors[0].per_frame
    for f in seq.frames:
        xml = (crossing / "frames" / f"sim_{f.index:04d}.xml").read_text()
        assert f"meshes/walker_{f.index:04d}.ply" in xml and "meshes/walker.ply" not in xml
        mine = read_ply(crossing / "meshes" / f"walker_{f.index:04d}.ply")
        assert np.allclose(mine.vertices, read_ply(ROOT / "examples" / "meshes" / f"walker_{f.index:04d}.ply").vertices)


# --- per-frame meshes ---------------------------------------------------------------------------------

def _ball(scale: float) -> Mesh:
    return builtin_mesh("sphere").scaled(scale)


def _spec(folder: Path, frames: int = 4) -> Path:
    """Per-frame object (a ball growing frame by frame: one UV layout) and a per-frame actor (a cone,
    then boxes: different meshes)."""
    for k in range(frames):
        write_ply(_ball(0.6 + 0.2 * k), folder / f"ball_{k}.ply")
        write_ply(builtin_mesh("traffic_cone") if k == 0 else builtin_mesh("sphere").scaled(0.3 + 0.1 * k),
                  folder / f"prop_{k:02d}.ply")
    spec = {"name": "grow", "frames": frames, "fps": 2,
            "camera": {"fov": 40, "resolution": [24, 24], "path": {"type": "static", "position": [0, 1.0, 4.0]},
                       "look_at": [0, 0.6, 0]},
            "object": {"asset": {"name": "ball", "mesh": "ball_{frame}.ply", "texture": {"resolution": [16, 8]}}},
            "actors": [{"asset": {"name": "prop", "mesh": "prop_{frame:02d}.ply"},
                        "path": {"type": "static", "position": [1.2, 0, -1.0]}}]}
    path = folder / "grow.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


@pytest.fixture(scope="module")
def grow(tmp_path_factory, mi):
    folder = tmp_path_factory.mktemp("grow")
    return init_scene(_spec(folder), folder / "scene", InitOptions(verify_spp=4)), folder


def test_per_frame_meshes_load_the_right_file(grow):
    scene, folder = grow
    for k in range(4):
        xml = (scene / "frames" / f"grad_{k:04d}.xml").read_text()
        assert f"meshes/object_{k:04d}.ply" in xml and f"meshes/prop_{k:04d}.ply" in xml
        assert np.allclose(read_ply(scene / "meshes" / f"object_{k:04d}.ply").vertices,
                           _ball(0.6 + 0.2 * k).vertices, atol=1e-6)
        written, given = read_ply(scene / "meshes" / f"prop_{k:04d}.ply"), read_ply(folder / f"prop_{k:02d}.ply")
        assert written.n_vertices == given.n_vertices
    assert not (scene / "meshes" / "object.ply").exists()
    areas = [int(read_mask(scene, k).sum()) for k in range(4)]
    assert areas == sorted(areas) and areas[-1] > 2 * areas[0], areas  # the ball grows in Mitsuba's masks


def test_per_frame_meshes_in_cycles(cycles, grow):
    from undream.sim import make_backend

    scene, _ = grow
    sim = make_backend("blender", scene, threads=2)
    try:
        for k in range(4):
            mask, mitsuba = sim.coverage(k, spp=16) > 0.5, read_mask(scene, k)
            iou = (mask & mitsuba).sum() / (mask | mitsuba).sum()
            assert iou > 0.85, f"frame {k}: Cycles' object against Mitsuba's, IoU {iou:.3f}"
    finally:
        sim.close()


def test_missing_per_frame_file_is_one_line(tmp_path):
    spec = _spec(tmp_path)
    (tmp_path / "prop_02.ply").unlink()
    out = tmp_path / "scene"
    res = CliRunner().invoke(__import__("undream.cli", fromlist=["main"]).main,
                             ["init", str(spec), "--out", str(out), "--no-progress", "--verify-spp", "1"])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert "actors[0].mesh ('prop')" in lines[0] and "prop_02.ply: file not found" in lines[0]
    assert not out.exists() and not list(tmp_path.glob(".scene*"))


def test_object_must_keep_its_uv_layout(tmp_path):
    spec = _spec(tmp_path)
    write_ply(builtin_mesh("trash_bin"), tmp_path / "ball_3.ply")  # another mesh in frame 3
    with pytest.raises(AssetError) as err:
        init_scene(spec, tmp_path / "scene", InitOptions(verify_spp=1))
    msg = str(err.value)
    assert "\n" not in msg and "ball_3.ply (frame 3) has another UV layout" in msg and "asset.mesh ('ball')" in msg
    assert not (tmp_path / "scene").exists()


def test_per_frame_mesh_spec():
    a = Asset("walker", "walk_{frame:04d}.ply")
    assert a.per_frame and a.mesh_at(7) == "walk_0007.ply" and Asset.from_json(a.to_json()) == a
    assert not Asset("bin", "builtin:trash_bin").per_frame
    for bad, message in (("walk_{step}.ply", "only field is {frame}"), ("builtin:x_{frame}", "builtin"),
                         ("walk_{frame:q}.ply", "only field is {frame}")):
        with pytest.raises(SpecError, match=message):
            Asset("walker", bad)


def test_scene_cache_swaps_per_frame_meshes_of_one_size(grow, mi):
    """Per-frame meshes with buffers of one size share a loaded scene (their vertices written per frame);
    a mesh of another size starts a group; every frame renders as its own file does."""
    from undream.color import srgb_to_linear
    from undream.render.differentiable import render_linear
    from undream.render.loading import load_scene, texture_param_key
    from undream.render.scene_cache import SceneCache
    from undream.scene.layout import frame_xml

    scene, _ = grow
    cache = SceneCache(scene, mi, frozen=False)
    tex = np.random.default_rng(1).uniform(0.1, 0.9, (8, 16, 3)).astype(np.float32)
    try:
        for k in (0, 1, 2, 3, 1):
            mine = render_linear(cache, k, tex, spp=2, seed=3, kind="grad")
            own = load_scene(mi, frame_xml(scene, "grad", k), spp=1, merge=False)
            params = mi.traverse(own)
            params[texture_param_key(params)] = mi.TensorXf(srgb_to_linear(tex))
            params.update()
            ref = np.array(mi.render(own, spp=2, seed=3), dtype=np.float32)
            diff = np.abs(mine - ref)  # vertices written into a loaded mesh: float rounding only
            assert diff.max() <= 5e-3 and diff.mean() <= 2e-4, (k, diff.max())
        assert cache.group_count("grad") == 2  # frame 0's cone; frames 1-3's balls and props of one size
    finally:
        cache.close()
