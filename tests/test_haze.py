"""The ``haze`` integrator renders what volpath renders (undream/render/haze.py).

A scene directory holds a frame in fog, rain or snow in ``with_haze``'s form; the same frame in its
volpath form (the medium and its null sphere, as ``scene_dict`` describes it) is in a twin of it
(scripts/haze_check.py's).
Both are rendered at many samples with independent seeds: an unbiased ``haze`` leaves per-pixel
differences from volpath of the size of the two renders' own noise, and a medium twice as thin (the
negative control) does not.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "haze_check.py"
_spec = importlib.util.spec_from_file_location("haze_check", _SCRIPT)
haze_check = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(haze_check)
volpath_twin = haze_check.volpath_twin  # the volpath form of a scene directory's frames in a medium

SPEC = """name: haze_{weather}
seed: 0
frames: 2
fps: 4
camera:
  fov: 40
  resolution: [16, 16]
  path: {{type: orbit, center: [0, 0, 0], radius: {radius}, height: 1.3, start_deg: 0, end_deg: 90}}
  look_at: object
  look_at_offset: [0, 0.5, 0]
object:
  asset: {{name: bin, mesh: builtin:trash_bin, texture: {{resolution: [16, 16], uv_scale: 1, init: [0.5, 0.5, 0.5]}}}}
  path: {{type: static, position: [0, 0, 0]}}
environment:
  weather: {weather}
  time_of_day: 12
  background: park
{extra}"""
SPP = 256


def _scene_dir(tmp_path: Path, weather: str, extra: str = "", radius: float = 3.2) -> Path:
    from undream.scenedir.init import InitOptions, init_scene

    spec = tmp_path / f"{weather}.yaml"
    spec.write_text(SPEC.format(weather=weather, extra=extra, radius=radius))
    return init_scene(spec, tmp_path / weather, InitOptions(verify_spp=4, progress=False))


def _render(mi, scene, seed: int) -> np.ndarray:
    return np.array(mi.render(scene, spp=SPP, seed=seed), dtype=np.float64)


def _excess(mi, haze, vol) -> float:
    """Mean squared difference haze − volpath over volpath − volpath (about 1 when they agree)."""
    v1, v2, h = _render(mi, vol, 1), _render(mi, vol, 2), _render(mi, haze, 3)
    return float(np.mean((h - v1) ** 2) / np.mean((v2 - v1) ** 2))


@pytest.mark.parametrize("weather, extra", [("fog", "  fog_density: 0.08\n"), ("snow", "")])
def test_haze_renders_what_volpath_renders(tmp_path, mi, weather, extra):
    from undream.render.loading import load_scene
    from undream.scene.layout import frame_xml

    root = _scene_dir(tmp_path, weather, extra)
    text = frame_xml(root, "sim", 0).read_text()
    assert 'type="haze"' in text and "fog_volume" not in text and "volpath" not in text
    haze = load_scene(mi, frame_xml(root, "sim", 0), SPP)
    vol = load_scene(mi, frame_xml(volpath_twin(root, tmp_path / "check"), "sim", 0), SPP)
    assert 0.6 < _excess(mi, haze, vol) < 1.4

    params = mi.traverse(haze)  # the negative control: a medium half as dense is told apart
    params["integrator.sigma_t"] = params["integrator.sigma_t"] * 0.5
    params.update()
    assert _excess(mi, haze, vol) > 2.0


def test_a_cached_frame_takes_its_own_medium(tmp_path, mi):
    """Frames of one structure share a loaded scene in the cache; the one written into it after the
    first renders with its own sphere and density, as its own file does."""
    from undream.render.differentiable import render_frozen
    from undream.render.loading import load_scene
    from undream.render.scene_cache import SceneCache
    from undream.scene.layout import frame_xml

    root = _scene_dir(tmp_path, "fog", "  fog_density: 0.15\n", radius=2.0)
    # frame 1: another density and another sphere, so the shared scene must change both
    text = frame_xml(root, "sim", 1).read_text()
    text = text.replace('name="sigma_t" value="0.15"', 'name="sigma_t" value="0.05"')
    text = text.replace('name="radius" value="42', 'name="radius" value="12')
    assert 'value="0.05"' in text and 'name="radius" value="12' in text
    frame_xml(root, "sim", 1).write_text(text)

    cache = SceneCache(root, mi)
    shared = [render_frozen(cache, "sim", cache.frame("sim", i), SPP, 7) for i in (0, 1)]
    assert cache.group_count("sim") == 1
    own = np.array(mi.render(load_scene(mi, frame_xml(root, "sim", 1), SPP), spp=SPP, seed=7))
    assert np.abs(shared[1] - own).max() < 1e-4
    assert np.abs(shared[0] - own).mean() > 10 * np.abs(shared[1] - own).mean()


def test_a_scene_without_a_medium_is_left_to_path(tmp_path, mi):
    from undream.scene.layout import frame_xml
    from undream.scene.mitsuba_scene import with_haze

    root = _scene_dir(tmp_path, "clear")
    assert 'type="path"' in frame_xml(root, "sim", 0).read_text()
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": 6}}
    assert with_haze(d) is d


def test_bad_haze_parameters_are_refused(mi):
    from undream.render.haze import register

    register(mi)
    base = {"type": "haze", "albedo": {"type": "rgb", "value": [0.8, 0.8, 0.8]}, "center": [0, 0, 0]}
    for bad in ({"sigma_t": 0.0, "radius": 10.0}, {"sigma_t": 0.1, "radius": -1.0}):
        with pytest.raises(Exception, match="sigma_t and radius must be > 0"):
            mi.load_dict({"type": "scene", "integrator": {**base, **bad}})


def test_the_check_scripts_twin_holds_volpath_frames(tmp_path, mi):
    """scripts/haze_check.py (and the first test here) judge a scene against a twin whose frames in a
    medium are volpath's."""
    from undream.scene.layout import frame_xml

    root = _scene_dir(tmp_path, "snow")
    twin = volpath_twin(root, tmp_path / "check")
    for index in (0, 1):
        text = frame_xml(twin, "sim", index).read_text()
        assert 'type="volpath"' in text and "fog_volume" in text and 'type="haze"' not in text
        assert frame_xml(twin, "grad", index).read_text() == frame_xml(root, "grad", index).read_text()
    assert 'type="haze"' in frame_xml(root, "sim", 0).read_text()  # the scene itself untouched
