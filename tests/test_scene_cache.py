"""The per-process scene cache: one loaded scene per group of equal frames, same pixels and gradients as before."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from undream.color import srgb_to_linear
from undream.render.differentiable import render_linear, texture_gradient
from undream.render.loading import load_scene, texture_param_key
from undream.render.scene_cache import SceneCache, structure_key
from undream.scene.layout import frame_xml
from undream.scene.poses import look_at
from undream.scenedir.init import InitOptions, init_scene
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform


def _frames(scene_dir) -> list[int]:
    return [f["index"] for f in json.loads((scene_dir / "sequence.json").read_text())["frames"]]


def _own_render(mi, scene_dir, kind, index, tex_linear, spp, seed):
    """Frame ``index`` rendered from its own, freshly loaded file (the reference path)."""
    scene = load_scene(mi, frame_xml(scene_dir, kind, index), spp=1, merge=False)
    params = mi.traverse(scene)
    params[texture_param_key(params)] = mi.TensorXf(tex_linear)
    params.update()
    return np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)


def test_structure_key_blanks_only_per_frame_numbers():
    a = '<matrix value="1 0 0 2"/><rgb name="irradiance" value="1, 2, 3"/><integer name="width" value="64"/>'
    b = '<matrix value="0 1 0 5"/><rgb name="irradiance" value="3, 2, 1"/><integer name="width" value="64"/>'
    c = '<matrix value="0 1 0 5"/><rgb name="irradiance" value="3, 2, 1"/><integer name="width" value="32"/>'
    assert structure_key(a) == structure_key(b)
    assert structure_key(a) != structure_key(c)  # film size is structure


def test_grouped_frames_render_like_their_own_files(example_scenes, mi):
    """Every example, both kinds: the shared scene shows each frame as its own file does.

    Moving meshes are rebuilt from updated vertices rather than loaded, so a
    few pixels where a ray grazes a triangle edge may take another path; the
    rest agree to float rounding.
    """
    rng = np.random.default_rng(0)
    for name, d in example_scenes.items():
        cache = SceneCache(d, mi, frozen=False)
        for kind in ("sim", "grad"):
            for index in _frames(d):
                active = cache.frame(kind, index)
                shape = active.params[active.texture_key].shape
                tex = rng.uniform(0.05, 0.95, shape).astype(np.float32)
                mine = render_linear(cache, index, tex, spp=2, seed=11, kind=kind)
                ref = _own_render(mi, d, kind, index, srgb_to_linear(tex), 2, 11)
                diff = np.abs(mine - ref)
                assert (diff > 1e-4).mean() <= 0.02 and diff.mean() <= 2e-4, (name, kind, index, diff.max())
            assert cache.group_count(kind) == 1, (name, kind)  # examples keep one structure per kind
        cache.close()


def test_frozen_render_equals_plain_render(example_scenes, mi):
    d = example_scenes["sphere_orbit"]  # fog, an actor, an orbiting camera
    frozen, plain = SceneCache(d, mi, frozen=True), SceneCache(d, mi, frozen=False)
    tex = np.full(frozen.frame("sim", 0).params[frozen.frame("sim", 0).texture_key].shape, 0.4, np.float32)
    for k in range(2):
        for index in _frames(d)[:4]:
            a = render_linear(frozen, index, tex, spp=2, seed=100 * k + index)
            b = render_linear(plain, index, tex, spp=2, seed=100 * k + index)
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    frozen.close()
    plain.close()


def test_gradient_equals_the_reference_prb_path(example_scenes, mi):
    """Same gradient as ``mi.render(scene, params, seed, seed_grad)`` + backward on the frame's own file."""
    import drjit as dr

    from undream.render.differentiable import srgb_decode_grad

    d = example_scenes["car_drive_by"]  # the object moves: its vertices change per frame
    cache = SceneCache(d, mi)
    rng = np.random.default_rng(1)
    for index in _frames(d)[:3]:
        active = cache.frame("grad", index)
        tex = rng.uniform(0.1, 0.9, active.params[active.texture_key].shape).astype(np.float32)
        w, h = (int(v) for v in active.params["sensor.film.crop_size"])
        g = rng.uniform(-1, 1, (h, w, 3)).astype(np.float32)
        mine = texture_gradient(cache, index, tex, g, spp=4, seed=5, seed_grad=6)

        scene = load_scene(mi, frame_xml(d, "grad", index), spp=1, merge=False)
        params = mi.traverse(scene)
        key = texture_param_key(params)
        params[key] = mi.TensorXf(srgb_to_linear(tex))
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, spp=4, seed=5, seed_grad=6)
        dr.backward(img * mi.TensorXf(g))
        ref = srgb_decode_grad(tex, np.array(dr.grad(params[key]), dtype=np.float32))
        del scene, params, img
        cos = float((mine * ref).sum() / (np.linalg.norm(mine) * np.linalg.norm(ref)))
        assert cos > 0.9999, (index, cos)
        assert np.linalg.norm(mine - ref) <= 1e-3 * np.linalg.norm(ref), index
    cache.close()


@pytest.fixture(scope="module")
def long_orbit(tmp_path_factory, mi):
    """14 frames orbiting a sphere, with an actor: as many files as a real sequence."""
    frames = tuple(
        Frame(i, Camera(Transform.from_rows(look_at([2.0 * np.sin(a), 1.2, 2.0 * np.cos(a)], [0, 0.5, 0])),
                        40.0, (16, 16)), Transform.identity(), Environment("clear", 10.0 + 0.3 * i))
        for i, a in enumerate(np.linspace(0, 2 * np.pi, 14, endpoint=False)))
    seq = Sequence("orbit", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(8, 4))), frames)
    return init_scene(seq, tmp_path_factory.mktemp("orbit") / "scene", InitOptions(verify_spp=1))


# Run in a fresh process: the probe reads the lowest free id of Dr.Jit's shape registry, so shapes freed
# and kept by earlier tests in the same process (holes in the ids) would make the count jump.
_SHAPES_PROBE = """
import gc, json, sys
import numpy as np
from undream.variant import mitsuba
from undream.render.differentiable import render_linear, texture_gradient
from undream.render.scene_cache import SceneCache
import drjit as dr

mi = mitsuba()
scene_dir, sharing = sys.argv[1], sys.argv[2] == "1"

def live_shapes():
    probe = mi.load_dict({"type": "scene", "s": {"type": "sphere"}})
    n = int(np.array(dr.reinterpret_array(mi.UInt32, probe.shapes_dr())).max())
    del probe
    gc.collect()
    return n - 1

gc.collect()
before = live_shapes()
cache = SceneCache(scene_dir, mi, max_loaded=4 if sharing else 10**6, share=sharing)
tex = np.full((4, 8, 3), 0.5, np.float32)
g = np.ones((16, 16, 3), np.float32)
counts = []
for index in [f["index"] for f in json.load(open(scene_dir + "/sequence.json"))["frames"]]:
    render_linear(cache, index, tex, spp=1, seed=index)
    texture_gradient(cache, index, tex, g, spp=1, seed=index, seed_grad=index + 1)
    counts.append(live_shapes() - before)
print(json.dumps({"counts": counts, "loaded": cache.loaded_count}))
cache.close()
"""


@pytest.mark.parametrize("sharing", [True, False], ids=["shared", "one-scene-per-frame"])
def test_registered_shapes_do_not_grow_with_the_sequence(long_orbit, sharing):
    """What a render traces over (every registered shape) stays that of one scene per kind.

    The per-frame cache the engine had before (one scene per frame kept
    loaded) is what ``max_loaded=∞`` and no sharing gives: the same count grows
    with the frames and the bound fails, so the test can tell the two apart.
    """
    res = subprocess.run([sys.executable, "-c", _SHAPES_PROBE, str(long_orbit), "1" if sharing else "0"],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    counts = out["counts"]
    per_scene = 2  # ground + object in each of the sim and grad scenes
    if sharing:
        assert max(counts) <= 2 * per_scene, counts
        assert out["loaded"] == 2
    else:
        assert max(counts) > 2 * per_scene, counts


# A cache collected by the garbage collector while another cache records its render: the collector
# runs __del__ wherever Python allocates, and the next test's init render was such a place (a CI
# worker died of it: "RecordThreadState::enqueue_host_func(): this function cannot be recorded!").
_COLLECTED_WHILE_RECORDING = """
import sys
import numpy as np
from undream.variant import mitsuba
import undream.render.differentiable as differentiable
from undream.render.differentiable import render_linear
from undream.render.scene_cache import SceneCache

mi = mitsuba()
tex = np.full((4, 8, 3), 0.5, np.float32)
old = SceneCache(sys.argv[1], mi)
render_linear(old, 0, tex, spp=1, seed=1)
render_linear(old, 0, tex, spp=1, seed=2)  # recorded and replayed: it holds a recording
assert old._frozen
plain_render = differentiable._render

def render_and_collect(*args):
    global old
    if old is not None:
        old.__del__()  # what the collector does to an unreachable cache here
        old = None
    return plain_render(*args)

differentiable._render = render_and_collect
new = SceneCache(sys.argv[1], mi)
img = render_linear(new, 0, tex, spp=1, seed=3)  # its first call records, and collects the old cache
print("rendered", float(img.mean()) > 0)
"""


# A dropped cache left to the collector (its LRU refers back to it, so nothing else frees it), and a
# collection at an allocation inside another cache's recording: the whole suite's run lost a test
# process to it. The collector must not run there; where it does, this script dies as that process did.
_COLLECTOR_INSIDE_A_RECORDING = """
import gc, sys
import numpy as np
from undream.variant import mitsuba
import undream.render.differentiable as differentiable
from undream.render.differentiable import render_linear
from undream.render.scene_cache import SceneCache

mi = mitsuba()
tex = np.full((4, 8, 3), 0.5, np.float32)
gc.disable()  # keep the dropped cache for the collection below
old = SceneCache(sys.argv[1], mi)
render_linear(old, 0, tex, spp=1, seed=1)
render_linear(old, 0, tex, spp=1, seed=2)
del old
gc.enable()
plain_render = differentiable._render
seen = []

def render_where_the_collector_may_run(*args):
    seen.append(gc.isenabled())
    if gc.isenabled():
        gc.collect()  # what the collector does at the next allocation when it is on
    return plain_render(*args)

differentiable._render = render_where_the_collector_may_run
new = SceneCache(sys.argv[1], mi)
img = render_linear(new, 0, tex, spp=1, seed=3)
print("collector on inside the recording:", any(seen), "rendered", float(img.mean()) > 0, "on after:", gc.isenabled())
"""


_DROPPED_CACHE = """
import gc, sys
import numpy as np
import drjit as dr
from undream.variant import mitsuba
from undream.render.differentiable import render_linear
from undream.render.scene_cache import SceneCache

mi = mitsuba()

def live_shapes():
    probe = mi.load_dict({"type": "scene", "s": {"type": "sphere"}})
    n = int(np.array(dr.reinterpret_array(mi.UInt32, probe.shapes_dr())).max())
    del probe
    return n - 1

gc.disable()  # what happens without the collector's help
before = live_shapes()
cache = SceneCache(sys.argv[1], mi, max_loaded=1)
tex = np.full((4, 8, 3), 0.5, np.float32)
render_linear(cache, 0, tex, spp=1, seed=1)
render_linear(cache, 0, tex, spp=1, seed=2, kind="grad")  # evicts the sim scene through the LRU
loaded = live_shapes()
del cache
print(before, loaded, live_shapes())
"""


def test_a_dropped_cache_frees_its_scenes_at_once(long_orbit):
    """Its scenes leave Dr.Jit's registry when the cache is dropped, not at the collector's next full
    pass: until then every render in the process traced over their shapes too."""
    res = subprocess.run([sys.executable, "-c", _DROPPED_CACHE, str(long_orbit)],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    before, loaded, after = map(int, res.stdout.split())
    assert loaded > before and after == before, (before, loaded, after)


def test_the_collector_never_runs_inside_a_recording(long_orbit):
    res = subprocess.run([sys.executable, "-c", _COLLECTOR_INSIDE_A_RECORDING, str(long_orbit)],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    last = res.stdout.strip().splitlines()[-1]
    assert last == "collector on inside the recording: False rendered True on after: True"


def test_a_cache_collected_while_another_records_does_not_kill_the_process(long_orbit):
    res = subprocess.run([sys.executable, "-c", _COLLECTED_WHILE_RECORDING, str(long_orbit)],
                         capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().splitlines()[-1] == "rendered True"
