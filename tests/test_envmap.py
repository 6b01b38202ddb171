"""A user's HDR environment map (``environment.envmap``): the spec's fields, ``undream init``'s checks
and copy, its orientation in Mitsuba (the lit side of a sphere faces the map's bright direction) and
in Cycles (the same side, the same mean radiance).

Maps are made here (32×16, numpy + Mitsuba's Bitmap): no downloads. Cycles tests skip without
Blender's Python (fail where ``UNDREAM_REQUIRE_SERVICES`` is set), as in tests/test_sim_blender.py.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from projection import centroid, project
from undream.errors import AssetError, SpecError
from undream.spec import Environment

ROOT = Path(__file__).resolve().parents[1]
H, W = 16, 32  # the test maps' height and width


def _pixel_of(direction: np.ndarray) -> tuple[int, int]:
    """(row, col) of a canonical direction in an equirectangular map as Mitsuba reads it:
    u = atan2(x, −z)/2π, v = acos(y)/π (row 0 straight up)."""
    x, y, z = np.asarray(direction, float) / np.linalg.norm(direction)
    u = (math.atan2(x, -z) / (2 * math.pi)) % 1.0
    v = math.acos(np.clip(y, -1, 1)) / math.pi
    return min(int(v * H), H - 1), int(u * W) % W


def _spot_map(direction: np.ndarray, dim: float = 0.03, bright: float = 60.0) -> np.ndarray:
    """A dark map with a bright 2×2-pixel spot around ``direction``."""
    img = np.full((H, W, 3), dim, np.float32)
    r, col = _pixel_of(direction)
    img[max(r - 1, 0):r + 1, [col - 1, col % W]] = bright  # the 2×2 texels nearest the direction
    return img


def _smooth_map() -> np.ndarray:
    """A sky brightening towards the zenith over a dark lower half, with a broad warm glow at +X."""
    v, u = np.meshgrid((np.arange(H) + 0.5) / H, (np.arange(W) + 0.5) / W, indexing="ij")
    y = np.cos(np.pi * v)
    dx = np.sin(2 * np.pi * u) * np.sin(np.pi * v)  # the x component of the texel's direction
    sky = np.where(y > 0, 0.25 + 0.35 * y, 0.05)
    glow = 1.5 * np.exp(8 * (dx - 1)) * (y > -0.1)
    return np.stack([sky + glow, sky + 0.8 * glow, sky * 1.3 + 0.5 * glow], axis=-1).astype(np.float32)


def _write(mi, img: np.ndarray, path: Path) -> Path:
    mi.Bitmap(np.ascontiguousarray(img, np.float32)).write(str(path))
    return path


def _spec(tmp_path: Path, environment, frames: int = 1, res: int = 32) -> Path:
    spec = {"name": "envmap", "seed": 0, "frames": frames,
            "camera": {"fov": 35, "resolution": [res, res], "path": {"type": "static", "position": [0, 1.2, 3.4]},
                       "look_at": [0, 0.5, 0]},
            "object": {"asset": {"name": "ball", "mesh": "builtin:sphere", "texture": {"resolution": [16, 8]}},
                       "path": {"type": "static", "position": [0, 0, 0]}},
            "environment": environment}
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


# --- the spec ------------------------------------------------------------------------------------

def test_environment_fields_round_trip_and_bad_values():
    env = Environment(envmap="/maps/sky.exr", envmap_scale=2.0, envmap_rotation_deg=-30)
    assert Environment.from_json(json.loads(json.dumps(env.to_json()))) == env
    assert "envmap" not in Environment().to_json()  # sequences without a map keep their files
    with pytest.raises(SpecError, match=r"envmap: must be the path of an \.exr or \.hdr"):
        Environment(envmap="sky.png")
    with pytest.raises(SpecError, match="envmap_scale"):
        Environment(envmap="sky.exr", envmap_scale=0)
    with pytest.raises(SpecError, match="envmap_rotation_deg"):
        Environment(envmap="sky.exr", envmap_rotation_deg=float("nan"))


def test_an_envmap_replaces_sky_and_sun_and_keeps_the_night_lamp():
    from undream.scene.environment import emitters

    day = emitters(Environment(envmap="/maps/sky.exr", envmap_scale=2.0, envmap_rotation_deg=90), np.zeros(3))
    assert set(day) == {"sky"} and day["sky"]["type"] == "envmap" and day["sky"]["scale"] == 2.0
    turn = np.array(day["sky"]["to_world"].m, float).reshape(4, 4)
    np.testing.assert_allclose(turn[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-12)  # +X turns towards −Z
    night = emitters(Environment("night", envmap="/maps/sky.exr"), np.zeros(3))
    assert set(night) == {"sky", "lamp"} and night["sky"]["type"] == "envmap"
    assert set(emitters(Environment(), np.zeros(3))) == {"sky", "sun"}


# --- undream init --------------------------------------------------------------------------------

def test_init_copies_the_map_and_records_its_source(tmp_path, mi):
    """A relative path resolves against the spec's folder; the scene directory holds the map (an
    .hdr becomes linear EXR) and refers to nothing outside itself; metadata.json names the source."""
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec import load_sequence

    (tmp_path / "maps").mkdir()
    img = _smooth_map()
    _write(mi, img, tmp_path / "maps" / "sky.hdr")
    spec = _spec(tmp_path, {"envmap": "maps/sky.hdr", "envmap_scale": 0.5, "envmap_rotation_deg": 20}, res=16)
    scene = init_scene(spec, tmp_path / "scene", InitOptions(verify_spp=1))
    copied = np.array(mi.Bitmap(str(scene / "textures" / "envmap.exr")), np.float32)
    assert copied.shape == (H, W, 3)
    assert np.allclose(copied, img, rtol=0.02, atol=1e-3)  # RGBE keeps about 1 % of each value
    env = load_sequence(scene / "sequence.json").frames[0].environment
    assert (env.envmap, env.envmap_scale, env.envmap_rotation_deg) == ("textures/envmap.exr", 0.5, 20.0)
    meta = json.loads((scene / "metadata.json").read_text())
    assert meta["envmap_sources"] == {"textures/envmap.exr": str((tmp_path / "maps" / "sky.hdr").resolve())}
    for xml in (scene / "frames").glob("*.xml"):
        assert 'value="../textures/envmap.exr"' in xml.read_text()
        assert str(tmp_path / "maps") not in xml.read_text()


def _nan_map(mi, path: Path) -> Path:
    img = _smooth_map()
    img[3, 4, 1] = np.nan
    return _write(mi, img, path)


def _negative_map(mi, path: Path) -> Path:
    img = _smooth_map()
    img[2, 2] = -0.5
    return _write(mi, img, path)


def _square_map(mi, path: Path) -> Path:
    return _write(mi, np.ones((16, 16, 3), np.float32), path)


def _not_an_image(mi, path: Path) -> Path:
    path.write_text("this is not an OpenEXR file\n")
    return path


@pytest.mark.parametrize("make, words", [
    (None, "environment map not found"),
    (_not_an_image, "not a readable .exr/.hdr image"),
    (_nan_map, "1 pixels hold NaN or infinite values"),
    (_negative_map, "1 pixels hold negative radiance"),
    (_square_map, "twice as wide as high, got 16×16"),
])
def test_bad_maps_are_one_line_and_write_nothing(tmp_path, mi, make, words):
    from undream.scenedir.init import init_scene

    path = tmp_path / "sky.exr"
    if make is not None:
        make(mi, path)
    spec = _spec(tmp_path, {"envmap": "sky.exr"})
    with pytest.raises(AssetError) as err:
        init_scene(spec, tmp_path / "scene")
    msg = str(err.value)
    assert "\n" not in msg and words in msg and "environment.envmap" in msg and str(path) in msg, msg
    assert not (tmp_path / "scene").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".scene")]


def test_cli_missing_map_is_one_line(tmp_path):
    spec = _spec(tmp_path, [{"envmap": "sky.exr"}, {"weather": "clear"}], frames=2)
    out = tmp_path / "scene"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "init", str(spec), "--out", str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert "environment[0].envmap" in lines[0] and str(tmp_path / "sky.exr") in lines[0]
    assert not out.exists()


# --- orientation and radiometry --------------------------------------------------------------------

BRIGHT = np.array([1.0, 0.7, 0.0])  # towards +X, 35° above the horizon
# (rotation about +Y in degrees, where the light then comes from): R_y(θ) turns +X towards −Z
TURNS = ((0.0, BRIGHT), (180.0, BRIGHT * [-1, 1, 1]), (-90.0, np.array([0.0, 0.7, 1.0])))


@pytest.fixture(scope="module")
def spot_scene(tmp_path_factory, mi):
    """Three frames of one sphere under the spot map, turned by each of :data:`TURNS`."""
    from undream.scenedir.init import InitOptions, init_scene

    tmp = tmp_path_factory.mktemp("spot")
    _write(mi, _spot_map(BRIGHT), tmp / "spot.exr")
    envs = [{"envmap": "spot.exr", "envmap_rotation_deg": t} for t, _ in TURNS]
    return init_scene(_spec(tmp, envs, frames=len(TURNS)), tmp / "scene", InitOptions(verify_spp=4))


def _lit_offset(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Where the sphere's light is, from its mask's centroid, in pixels (x right, y down)."""
    lum = img.mean(axis=2) * mask
    rows, cols = np.indices(mask.shape)
    lit = np.array([(cols * lum).sum(), (rows * lum).sum()]) / lum.sum() + 0.5
    return lit - centroid(mask)


def _expected_offset(scene: Path, index: int, direction: np.ndarray) -> np.ndarray:
    """The image direction in which ``direction`` points from the sphere's centre (independent projection)."""
    from projection import load
    from undream.scene.mesh import read_ply

    seq = load(scene)
    cam = seq["frames"][index]["camera"]
    centre = read_ply(scene / "meshes" / "object.ply").vertices.mean(axis=0)
    a, b = project(np.array([centre, centre + 0.5 * direction / np.linalg.norm(direction)]), cam)[0]
    return b - a


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def _check_orientation(scene: Path, frames: list[np.ndarray], who: str) -> None:
    from undream.scenedir.verify import read_mask

    means = []
    for i, (turn, direction) in enumerate(TURNS):
        mask = read_mask(scene, i)
        means.append(frames[i][mask].mean())
        if turn == -90.0:
            continue  # lit from the camera's side: no sideways offset to test
        got, expect = _lit_offset(frames[i], mask), _expected_offset(scene, i, direction)
        print(f"{who}, turned {turn:+.0f}°: lit side {got.round(2)} px, expected towards {expect.round(2)}")
        assert _cos(got, expect) > 0.8, f"{who}, turned {turn}°: lit side {got} px, light towards {expect}"
    assert means[2] > 1.5 * max(means[:2]), f"{who}: lit from the front should be brightest, {means}"


def test_mitsuba_lights_the_side_facing_the_bright_direction(spot_scene):
    from undream.sim import make_backend

    tex = np.full((8, 16, 3), 0.7, np.float32)
    sim = make_backend("mitsuba", spot_scene)
    _check_orientation(spot_scene, [sim.render(i, tex, 64, 1) for i in range(len(TURNS))], "Mitsuba")



def test_cycles_lights_the_same_side(cycles, spot_scene):
    from undream.sim import make_backend

    tex = np.full((8, 16, 3), 0.7, np.float32)
    sim = make_backend("blender", spot_scene, threads=2)
    try:
        frames = [sim.render(i, tex, 64, 1) for i in range(len(TURNS))]
    finally:
        sim.close()
    _check_orientation(spot_scene, frames, "Cycles")


def test_cycles_mean_radiance_matches_mitsuba(cycles, tmp_path, mi):
    """A smooth map, scaled and turned: the frame's mean linear radiance Cycles / Mitsuba within 5 %,
    and the sky's own pixels (where the camera sees the map) within 5 % too; a frame without a map
    after it gets its procedural sky and sun back (3 %), and the map frame rendered again is the same."""
    from undream.scenedir.init import InitOptions, init_scene
    from undream.sim import make_backend

    _write(mi, _smooth_map(), tmp_path / "sky.exr")
    envs = [{"envmap": "sky.exr", "envmap_scale": 1.7, "envmap_rotation_deg": 30},
            {"weather": "clear", "time_of_day": 15.0}]
    scene = init_scene(_spec(tmp_path, envs, frames=2), tmp_path / "scene", InitOptions(verify_spp=1))
    tex = np.full((8, 16, 3), 0.6, np.float32)
    mit = make_backend("mitsuba", scene)
    a, a_plain = mit.render(0, tex, 256, 2), mit.render(1, tex, 64, 2)
    sim = make_backend("blender", scene, threads=2)
    try:
        b, b_plain, b_again = sim.render(0, tex, 256, 2), sim.render(1, tex, 64, 2), sim.render(0, tex, 256, 2)
    finally:
        sim.close()
    ratio = b.mean() / a.mean()
    top = b[:6].mean() / a[:6].mean()  # the upper rows: sky seen directly
    plain = b_plain.mean() / a_plain.mean()
    print(f"Cycles / Mitsuba mean radiance {ratio:.3f}; sky rows {top:.3f}; the next frame without a map {plain:.3f}")
    assert abs(ratio - 1) < 0.05 and abs(top - 1) < 0.05
    assert abs(plain - 1) < 0.03
    assert np.array_equal(b_again, b)


def test_eot_light_scale_scales_the_envmap_and_turns_are_per_frame(spot_scene, mi):
    """EOT's light factor scales an envmap (``sky.scale``) in the gradient scene; frames that differ only
    in the map's turn share one loaded scene, and each shows its own turn."""
    from undream.render.differentiable import render_linear
    from undream.render.jitter import Conditions
    from undream.render.scene_cache import SceneCache

    tex = np.full((8, 16, 3), 0.5, np.float32)
    scenes = SceneCache(spot_scene, mi, frozen=False)
    fresh = SceneCache(spot_scene, mi, frozen=False, share=False)
    try:
        plain = render_linear(scenes, 0, tex, spp=4, seed=11, kind="grad")
        brighter = render_linear(scenes, 0, tex, spp=4, seed=11, kind="grad",
                                 conditions=Conditions(np.zeros(3), np.eye(3), np.eye(3), 1.25))
        np.testing.assert_allclose(brighter, 1.25 * plain, rtol=1e-4, atol=1e-6)
        for i in (1, 2, 0):
            np.testing.assert_allclose(render_linear(scenes, i, tex, spp=4, seed=11),
                                       render_linear(fresh, i, tex, spp=4, seed=11), rtol=1e-5, atol=1e-6)
        assert scenes.group_count("sim") == 1
    finally:
        scenes.close()
        fresh.close()


# --- the night lamp ----------------------------------------------------------------------------------

def test_night_lamp_fields_round_trip_and_refuse_a_lamp_by_day():
    moved = Environment("night", lamp_offset=(-2.0, 4.0, 1.0), lamp_intensity=(40, 20, 5))
    assert Environment.from_json(json.loads(json.dumps(moved.to_json()))) == moved
    assert "lamp_offset" not in Environment("night").to_json()  # the default lamp's scenes keep their files
    with pytest.raises(SpecError, match=r"lamp_offset: .*lights the night only; weather is 'clear'"):
        Environment("clear", lamp_offset=(1, 2, 3))
    with pytest.raises(SpecError, match=r"lamp_intensity: .*>= 0, not all 0"):
        Environment("night", lamp_intensity=(1, -1, 0))
    with pytest.raises(SpecError, match=r"lamp_offset\[2\]"):
        Environment("night", lamp_offset=(1, 2, float("nan")))


def test_a_moved_and_coloured_night_lamp_lights_its_own_side(tmp_path, mi):
    """`undream init` of a night spec whose lamp moves to the other side and turns blue: the render
    is lit from the lamp's side (projected independently) and takes the lamp's colour."""
    from undream.scenedir.init import InitOptions, init_scene
    from undream.scenedir.verify import read_mask
    from undream.sim import make_backend

    lamps = [((2.5, 6.0, 2.5), (30.0, 25.0, 18.0)), ((-2.5, 3.0, 0.5), (2.0, 4.0, 40.0))]
    envs = [{"weather": "night", "lamp_offset": list(o), "lamp_intensity": list(c)} for o, c in lamps]
    scene = init_scene(_spec(tmp_path, envs, frames=2), tmp_path / "scene", InitOptions(verify_spp=4))
    sim = make_backend("mitsuba", scene)
    tex = np.full((8, 16, 3), 0.7, np.float32)
    centre = np.zeros(3)  # the sphere stands at the origin: the lamp's offset is its direction
    for i, (offset, colour) in enumerate(lamps):
        img, mask = sim.render(i, tex, 64, 1), read_mask(scene, i)
        got, expect = _lit_offset(img, mask), _expected_offset(scene, i, np.asarray(offset) - centre)
        assert _cos(got, expect) > 0.8, f"lamp {offset}: lit side {got} px, lamp towards {expect}"
        rgb = img[mask].mean(axis=0)
        assert np.argmax(rgb) == np.argmax(colour), f"lamp {colour}: the sphere's mean colour {rgb}"
