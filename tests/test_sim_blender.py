"""The ``blender`` simulator (Cycles in its own process): wire format, bad input, agreement with
Mitsuba and with an independent projection, texture orientation and swaps, seeds, an attack run.

Tests that render need Blender's Python (``.venv-blender``, made by
``deploy/setup.sh``, or ``$UNDREAM_BLENDER_PYTHON``); without it they skip
with the reason, and fail instead where ``UNDREAM_REQUIRE_SERVICES`` is set
(CI), so CI never passes by skipping.
"""
from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.ndimage import binary_dilation

from farm_support import make_victim
from projection import centroid, load, visible_mask
from undream.errors import RenderError, SpecError
from undream.scenedir.verify import read_mask
from undream.sim import make_backend
from undream.sim.blender_protocol import ProtocolError, read_message, write_message
from undream.spec.run import RunConfig

ROOT = Path(__file__).resolve().parents[1]
MIN_PIXELS = 12  # as tests/test_init.py: fewer pixels say little about a centroid



# --- no Blender needed ---------------------------------------------------------------------------

def test_protocol_round_trip_and_bad_streams():
    buf = io.BytesIO()
    img = np.arange(24, dtype=np.float32).reshape(2, 4, 3)
    write_message(buf, {"cmd": "render", "index": 3}, img)
    write_message(buf, {"cmd": "quit"})
    buf.seek(0)
    head, arr = read_message(buf)
    assert head["cmd"] == "render" and head["shape"] == [2, 4, 3] and np.array_equal(arr, img)
    assert read_message(buf) == ({"cmd": "quit"}, None)
    with pytest.raises(ProtocolError, match="stream closed"):
        read_message(buf)
    cut = io.BytesIO()
    write_message(cut, {"x": 1}, img)
    with pytest.raises(ProtocolError, match="stream closed after"):
        read_message(io.BytesIO(cut.getvalue()[:-5]))
    lying = cut.getvalue().replace(b"[2, 4, 3]", b"[2, 4, 2]")
    with pytest.raises(ProtocolError, match="does not hold a float32 array"):
        read_message(io.BytesIO(lying))


def test_run_config_sim_field():
    assert RunConfig(scene="s").sim == "mitsuba"
    cfg = RunConfig(scene="s", sim="blender")
    assert RunConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    with pytest.raises(SpecError, match="sim.*cycles"):
        RunConfig(scene="s", sim="cycles")


def test_missing_interpreter_is_one_line(tmp_path):
    missing = tmp_path / "no-blender" / "python"
    with pytest.raises(RenderError) as err:
        make_backend("blender", tmp_path, python=missing)
    msg = str(err.value)
    assert "\n" not in msg and str(missing) in msg and "setup.sh" in msg and "UNDREAM_BLENDER_PYTHON" in msg


def test_cli_run_without_bpy_writes_nothing(tmp_path):
    """``sim: blender`` without Blender's Python: one line naming the run file and the interpreter, exit 2."""
    run = tmp_path / "run.yaml"
    run.write_text(yaml.safe_dump({"scene": str(ROOT / "examples" / "bin_park.yaml"), "sim": "blender",
                                   "attack": {"name": "pgd", "eps": 8, "steps": 1}}))
    missing = tmp_path / "nowhere" / "python3.11"
    out = tmp_path / "out"
    env = {**__import__("os").environ, "UNDREAM_BLENDER_PYTHON": str(missing)}
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(run), "--out", str(out), "--no-progress"],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1 and "run.yaml" in lines[0] and "sim: blender" in lines[0] and str(missing) in lines[0]
    assert not out.exists()


def test_a_worker_gives_cycles_its_drjit_share(tmp_path):
    """A farm worker process with ``drjit_threads: 1`` renders Cycles on 1 thread too, unless
    ``UNDREAM_BLENDER_THREADS`` says otherwise (no Blender needed: the count the backend would pass)."""
    code = ("from undream.settings import Settings; from workers.runtime import init_process; "
            f"local = init_process(Settings(drjit_threads=1, cache_dir={str(tmp_path)!r})); "
            "from undream.sim import backend_options; from undream.sim.blender import cycles_threads; "
            "print(cycles_threads(backend_options('blender', local)['threads']))")
    env = {k: v for k, v in __import__("os").environ.items() if k != "UNDREAM_BLENDER_THREADS"}
    for extra, expect in (({}, "1"), ({"UNDREAM_BLENDER_THREADS": "3"}, "3")):
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                             env={**env, **extra}, timeout=300)
        assert res.returncode == 0, res.stderr
        assert res.stdout.strip().splitlines()[-1] == expect


# --- with Blender ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bin_park(cycles, example_scenes):
    return example_scenes["bin_park"]


def test_object_where_mitsuba_and_projection_put_it(cycles, example_scenes):
    """Every frame of every example: Cycles' coverage mask against the independent projection
    (centroid within 1.5 px) and against Mitsuba's mask (IoU ≥ 0.9)."""
    checked, worst_err, worst_iou = 0, 0.0, 1.0
    for name, d in example_scenes.items():
        sim = make_backend("blender", d, threads=2)
        seq = load(d)
        try:
            for f in seq["frames"]:
                mask = sim.coverage(f["index"], spp=64) > 0.5
                mitsuba = read_mask(d, f["index"])
                expect = visible_mask(d, f, seq)
                union = (mask | mitsuba).sum()
                if union >= MIN_PIXELS:
                    iou = (mask & mitsuba).sum() / union
                    worst_iou = min(worst_iou, iou)
                    assert iou >= 0.9, f"{name} frame {f['index']}: mask IoU with Mitsuba {iou:.3f}"
                if expect.sum() < MIN_PIXELS:
                    continue
                err = float(np.linalg.norm(centroid(mask) - centroid(expect)))
                worst_err = max(worst_err, err)
                assert err <= 1.5, f"{name} frame {f['index']}: Cycles' object centroid off by {err:.2f} px"
                checked += 1
        finally:
            sim.close()
    print(f"frames checked {checked}; worst centroid error {worst_err:.3f} px; worst IoU {worst_iou:.3f}")
    assert checked >= 30


def _ramps(shape: tuple[int, int, int], flip_v: bool = False) -> np.ndarray:
    """sRGB texture: red grows along u (columns), green along v (rows, down), blue constant."""
    h, w, _ = shape
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
    v = 1 - v if flip_v else v
    return np.stack([0.15 + 0.8 * u, 0.15 + 0.8 * v, np.full_like(u, 0.3)], axis=-1).astype(np.float32)


def _chroma(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    px = img[mask]
    return px[:, :2] / px.sum(axis=1, keepdims=True)


def test_texture_orientation_matches_mitsuba(bin_park):
    """The same u/v-ramp texture lands the same way round in both renderers; a v-flipped one would not."""
    from undream.spec import load_sequence

    seq = load_sequence(bin_park / "sequence.json")
    tex = _ramps(seq.texture.shape)
    mask = read_mask(bin_park, 0)
    blender = make_backend("blender", bin_park, threads=2)
    mitsuba = make_backend("mitsuba", bin_park)
    try:
        cyc = _chroma(blender.render(0, tex, 32, 3), mask)
    finally:
        blender.close()
    mit = _chroma(mitsuba.render(0, tex, 32, 3), mask)
    flipped = _chroma(mitsuba.render(0, _ramps(seq.texture.shape, flip_v=True), 32, 3), mask)
    corr = [np.corrcoef(cyc[:, k], mit[:, k])[0, 1] for k in (0, 1)]
    corr_flipped = np.corrcoef(cyc[:, 1], flipped[:, 1])[0, 1]
    print(f"chromaticity correlation u {corr[0]:.3f} v {corr[1]:.3f}; against a v-flipped texture {corr_flipped:.3f}")
    assert min(corr) > 0.8 and corr_flipped < 0.5


def test_texture_swap_seed_and_radiometry(bin_park):
    """A new texture changes the object's pixels only; a seed reproduces a frame; radiance matches Mitsuba's."""
    from undream.spec import load_sequence

    seq = load_sequence(bin_park / "sequence.json")
    grey = np.full(seq.texture.shape, 0.5, np.float32)
    white = np.ones(seq.texture.shape, np.float32)
    mask = read_mask(bin_park, 0)
    sim = make_backend("blender", bin_park, threads=2)
    try:
        a = sim.render(0, grey, 8, 11)
        again = sim.render(0, grey, 8, 11)
        other_seed = sim.render(0, grey, 8, 12)
        lighter = sim.render(0, white, 8, 11)
        with pytest.raises(RenderError, match="frame 999"):
            sim.render(999, grey, 8, 11)
        assert sim.render(0, grey, 8, 11).shape == a.shape  # still serving after the error
        assert sim.versions()["blender"] == "5.0.1"
        reference = sim.render(0, grey, 64, 1)
    finally:
        sim.close()
    assert np.array_equal(a, again)
    assert not np.array_equal(a, other_seed)
    assert (lighter[mask].mean(axis=1) > a[mask].mean(axis=1) * 1.3).mean() > 0.95
    far = ~binary_dilation(mask, iterations=8)  # background clear of the object and its bounce light
    assert np.abs(lighter[far] - a[far]).max() < 0.05
    mit = make_backend("mitsuba", bin_park).render(0, grey, 64, 1)
    for region in (mask, ~mask):
        rel = abs(reference[region].mean() - mit[region].mean()) / mit[region].mean()
        assert rel < 0.05, f"mean radiance differs by {rel:.1%}"


def test_a_dead_server_is_restarted_and_reproduces_the_frame(bin_park):
    from undream.spec import load_sequence

    grey = np.full(load_sequence(bin_park / "sequence.json").texture.shape, 0.5, np.float32)
    sim = make_backend("blender", bin_park, threads=2)
    try:
        first = sim.render(0, grey, 4, 1)
        sim._proc.kill()  # Blender gone between two renders
        sim._proc.wait()
        assert np.array_equal(sim.render(0, grey, 4, 1), first)  # a fresh server, the same frame
    finally:
        sim.close()


def test_a_server_that_dies_is_one_line(tmp_path, monkeypatch):
    """An interpreter that imports bpy but whose server exits at once: one line naming the exit code
    and the server's last output (no Blender needed)."""
    fake = tmp_path / "python"
    fake.write_text('#!/bin/sh\n[ "$1" = "-c" ] && exit 0\necho "Segmentation fault (core dumped)" >&2\nexit 139\n')
    fake.chmod(0o755)
    sim = make_backend("blender", tmp_path, python=fake)
    with pytest.raises(RenderError) as err:
        sim.render(0, np.zeros((2, 2, 3), np.float32), 1, 0)
    msg = str(err.value)
    assert "\n" not in msg and "exit code 139" in msg and "Segmentation fault" in msg, msg


@pytest.fixture(scope="module")
def victim_dir(tmp_path_factory):
    """A tiny random HF ResNet over the built-in classes, saved locally (no network)."""
    return make_victim(tmp_path_factory.mktemp("victim") / "tiny")


def test_attack_run_with_cycles_frames(cycles, victim_dir, tmp_path, mi):
    """``sim: blender`` end to end: Cycles renders the attack's and the evaluation's frames, Mitsuba's
    gradient scene carries the image gradient to the texture, and the texture moves."""
    from scheduler.local import run_local
    from undream.scene.poses import look_at
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

    frames = tuple(Frame(i, Camera(Transform.from_rows(look_at([1.6 * np.sin(a), 1.2, 2.4 * np.cos(a)],
                                                               [0, 0.5, 0])), 40.0, (24, 24)),
                         Transform.identity(), Environment("clear", 12.0))
                   for i, a in enumerate([0.0, 0.5, 1.0]))
    seq = Sequence("cyc", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    scene = init_scene(seq, tmp_path / "scene", InitOptions(verify_spp=1))
    cfg = RunConfig(scene=str(scene), name="cyc", victim=victim_dir, loss="ce", sim="blender",
                    attack={"name": "pgd", "eps": 32.0, "steps": 2}, sim_spp=4, grad_spp=4, eval_spp=4,
                    seed=3, holdout="none")
    res = run_local(cfg, tmp_path / "out", progress=False)
    meta = json.loads((tmp_path / "out" / "metadata.json").read_text())
    assert meta["versions"]["simulator"] == "blender" and meta["versions"]["blender"] == "5.0.1"
    assert len(list((tmp_path / "out" / "frames_adversarial").glob("*.png"))) == 3
    assert len(res["loss_per_iteration"]) == 2 and all(np.isfinite(res["loss_per_iteration"]))
    final = np.load(tmp_path / "out" / "texture_final.npy")
    assert np.abs(final - 0.5).max() > 1 / 255  # the Cycles-driven gradient reached the texture


def test_every_preset_agrees_with_mitsuba(cycles, tmp_path, mi):
    """One sequence whose frames change the weather (clear → ... → snow): Cycles switches sun, sky,
    lamp and haze per frame, and each frame's mean linear radiance is Mitsuba's within 3 % (media:
    8 %; measured on bin_orbit at 64 spp: 0.0–0.1 % without a medium, +5.5 % fog)."""
    from undream.scene.poses import look_at
    from undream.scenedir.init import InitOptions, init_scene
    from undream.spec import WEATHERS, Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform

    cam = Camera(Transform.from_rows(look_at([1.8, 1.3, 2.6], [0, 0.5, 0])), 50.0, (24, 24))
    frames = tuple(Frame(i, cam, Transform.identity(), Environment(w, 15.0, "park")) for i, w in enumerate(WEATHERS))
    seq = Sequence("presets", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    scene = init_scene(seq, tmp_path / "scene", InitOptions(verify_spp=1))
    tex = np.full(seq.texture.shape, 0.6, np.float32)
    mit = make_backend("mitsuba", scene)
    sim = make_backend("blender", scene, threads=2)
    try:
        for f in frames:
            spp = 256 if f.environment.weather in ("fog", "rain", "snow") else 64
            a, b = mit.render(f.index, tex, spp, 5).mean(), sim.render(f.index, tex, spp, 5).mean()
            tol = 0.08 if f.environment.weather in ("fog", "rain", "snow") else 0.03
            print(f"{f.environment.weather}: Cycles / Mitsuba mean radiance {b / a:.3f}")
            assert abs(b / a - 1) < tol, f"{f.environment.weather}: Cycles / Mitsuba = {b / a:.3f}"
    finally:
        sim.close()


def test_cycles_threads_follow_the_setting(cycles, tmp_path, mi):
    """The server renders with the thread count it was given (``threads``, else
    ``$UNDREAM_BLENDER_THREADS`` read at the edge, else this process's Dr.Jit thread count; a farm worker passes
    ``drjit_threads``), and reports what Cycles uses."""
    import drjit as dr

    from undream.scene.poses import look_at
    from undream.scenedir.init import InitOptions, init_scene
    from undream.sim.blender import cycles_threads
    from undream.spec import Asset, Camera, Frame, Sequence, TextureParam, Transform

    cam = Camera(Transform.from_rows(look_at([1.5, 1.2, 2.0], [0, 0.5, 0])), 40.0, (8, 8))
    seq = Sequence("t", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(4, 4))),
                   (Frame(0, cam, Transform.identity()),))
    scene = init_scene(seq, tmp_path / "scene", InitOptions(verify_spp=1))
    from undream.settings import load_local
    from undream.sim import backend_options

    before = dr.thread_count()
    try:
        dr.set_thread_count(3)
        assert cycles_threads() == 3 and cycles_threads(5) == 5
        set_by_user = backend_options("blender", load_local({"UNDREAM_BLENDER_THREADS": "2"}))["threads"]
        assert cycles_threads(set_by_user) == 2
        for given, expect in ((set_by_user, 2), (1, 1)):
            sim = make_backend("blender", scene, threads=given)
            try:
                assert sim.started().server_threads == expect
                assert sim.render(0, np.full((4, 4, 3), 0.5, np.float32), 1, 0).shape == (8, 8, 3)
            finally:
                sim.close()
    finally:
        dr.set_thread_count(before)
