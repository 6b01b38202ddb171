"""The ``unreal`` simulator against a stand-in editor: the spool protocol end to end.

Unreal cannot run here. The stand-in is ``deploy/unreal/render_texture.py``'s
own :class:`Worker` and :class:`Spool` (everything of the editor script but
the class that calls ``unreal``), ticked by a thread, with a renderer that
answers from recorded frames (``tests/fixtures/unreal_frames``, written by
``tests/fixtures/make_unreal_frames.py``) and paints the object's pixels with
the mean colour of the texture it was sent.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from undream.color import srgb_to_linear, to_uint8
from undream.errors import RenderError, SpecError
from undream.sim import check_simulator, make_backend
from undream.spec import Asset, Camera, Frame, Sequence, TextureParam, Transform, save_sequence
from undream.spec.run import RunConfig

ROOT = Path(__file__).resolve().parents[1]
FRAMES = Path(__file__).resolve().parent / "fixtures" / "unreal_frames"
W, H = 24, 16


def _editor_script():
    spec = importlib.util.spec_from_file_location("render_texture", ROOT / "deploy" / "unreal" / "render_texture.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["render_texture"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


rt = _editor_script()


class RecordedFrames:
    """A renderer standing in for Unreal: the recorded frame, the object painted with the texture's mean."""

    def __init__(self, fmt: str = "png", answer: str = "frame"):
        self.space = "linear" if fmt == "exr" else "srgb"
        self.fmt, self.answer = fmt, answer
        self.jobs: list = []
        self.textures: list[np.ndarray] = []

    def engine(self) -> str:
        return "5.4.4-fake"

    def render(self, job, done) -> None:
        self.jobs.append(job)
        tex = np.asarray(Image.open(job.texture).convert("RGB"))
        self.textures.append(tex)
        img = np.asarray(Image.open(FRAMES / f"frame_{job.frame:04d}.png").convert("RGB")).copy()
        mask = np.asarray(Image.open(FRAMES / f"mask_{job.frame:04d}.png")) > 0
        img[mask] = np.rint(tex.reshape(-1, 3).mean(axis=0)).astype(np.uint8)
        out = job.texture.parent.parent / f"render-{job.id}.{self.fmt}"
        if self.answer == "raise":
            raise RuntimeError("Movie Render Queue is already rendering")
        if self.answer == "small":
            img = img[:-1]
        if self.fmt == "exr":
            from undream.variant import mitsuba

            mitsuba().Bitmap(srgb_to_linear(img / 255.0)).write(str(out))
        else:
            Image.fromarray(img).save(out)
        done(out, None)


class Editor:
    """The editor script's Worker on a spool, ticked by a thread (as Slate ticks it in the editor)."""

    def __init__(self, spool: Path, renderer):
        self.spool = rt.Spool(spool)
        self.spool.announce({"engine": "5.4.4-fake", "project": "Test.uproject"})
        self.worker = rt.Worker(self.spool, renderer)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self.stop.is_set():
            self.worker.tick()
            time.sleep(0.005)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)


@pytest.fixture
def scene(tmp_path) -> Path:
    """A scene directory's sequence.json: 3 frames at 24×16 px (all the backend reads)."""
    cam = Camera(Transform.from_rows(np.eye(4)), 50.0, (W, H))
    seq = Sequence("street", Asset("bin", "builtin:trash_bin", texture=TextureParam(resolution=(8, 4))),
                   tuple(Frame(i, cam, Transform.identity()) for i in range(3)))
    (tmp_path / "scene").mkdir()
    save_sequence(seq, tmp_path / "scene" / "sequence.json")
    return tmp_path / "scene"


@pytest.fixture
def spool(tmp_path) -> Path:
    (tmp_path / "spool").mkdir()
    return tmp_path / "spool"


def _texture(rgb) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, np.float32), (4, 8, 3)).copy()


def _expected(frame: int, texture: np.ndarray) -> np.ndarray:
    img = np.asarray(Image.open(FRAMES / f"frame_{frame:04d}.png").convert("RGB")).copy()
    mask = np.asarray(Image.open(FRAMES / f"mask_{frame:04d}.png")) > 0
    img[mask] = np.rint(to_uint8(texture).reshape(-1, 3).mean(axis=0)).astype(np.uint8)
    return srgb_to_linear(img / 255.0)


@pytest.mark.parametrize("fmt", ["png", "exr"])
def test_frames_come_back_from_the_editor(scene, spool, fmt):
    """Request written, texture passed, frame read back (PNG: sRGB decoded; EXR: linear as is), files cleaned."""
    renderer = RecordedFrames(fmt)
    sim = make_backend("unreal", scene, spool=spool, timeout_s=20)
    red = _texture([0.8, 0.1, 0.1])
    ramp = np.random.default_rng(0).random((4, 8, 3)).astype(np.float32)
    with Editor(spool, renderer):
        a = sim.render(1, red, spp=4, seed=7)
        b = sim.render(2, ramp, spp=2, seed=8)
    assert a.dtype == np.float32 and a.shape == (H, W, 3)
    np.testing.assert_allclose(a, _expected(1, red), atol=1e-6)
    np.testing.assert_allclose(b, _expected(2, ramp), atol=1e-6)
    job = renderer.jobs[0]
    assert (job.frame, job.resolution, job.spp, job.seed, job.sequence) == (1, (W, H), 4, 7, "street")
    assert np.array_equal(renderer.textures[1], to_uint8(ramp))  # the texture arrived texel for texel
    assert not any((spool / "requests").iterdir()) and not any((spool / "responses").iterdir())
    assert sim.versions()["unreal"] == "5.4.4-fake"


def test_no_editor_is_a_one_line_timeout(scene, spool):
    sim = make_backend("unreal", scene, spool=spool, timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(RenderError) as err:
        sim.render(0, _texture([0.5, 0.5, 0.5]), 1, 0)
    msg = str(err.value)
    assert time.monotonic() - t0 < 5
    assert "\n" not in msg and "frame 0: no answer from the editor in 0.3 s" in msg and "not taken" in msg
    assert str(spool) in msg and "render_texture.py" in msg
    assert not any((spool / "requests").iterdir())  # a late editor finds nothing stale


def _answer_with(spool: Path, write) -> threading.Thread:
    """A bad editor: waits for one request and answers it with ``write(responses, rid)``."""
    def run():
        for _ in range(400):
            reqs = list((spool / "requests").glob("*.json"))
            if reqs:
                write(spool / "responses", reqs[0].stem)
                return
            time.sleep(0.01)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def _response(rid: str, **over) -> str:
    return json.dumps({"format": "undream-unreal-response", "version": 1, "id": rid, "image": f"{rid}.png",
                       "space": "srgb", **over})


@pytest.mark.parametrize("case, message", [
    ("not json", "malformed response .*: not JSON"),
    ("other id", "must be a JSON object with \"id\""),
    ("no image", r"cannot read .*\.png"),
    ("bad name", "\"image\" must name an .exr or .png file"),
    ("wrong size", "is 24×15 px, the frame's camera renders 24×16"),
    ("error", "the editor says: Movie Render Queue is already rendering"),
])
def test_bad_responses_are_one_line(scene, spool, case, message):
    def write(responses: Path, rid: str) -> None:
        answer = responses / f"{rid}.json"
        if case == "not json":
            answer.write_text("{ truncated")
        elif case == "other id":
            answer.write_text(_response("someone-else"))
        elif case == "no image":
            answer.write_text(_response(rid))
        elif case == "bad name":
            answer.write_text(_response(rid, image="../../etc/passwd"))
        elif case == "wrong size":
            Image.new("RGB", (W, H - 1)).save(responses / f"{rid}.png")
            answer.write_text(_response(rid))
        else:
            answer.write_text(json.dumps({"id": rid, "error": "Movie Render Queue is\nalready rendering"}))

    sim = make_backend("unreal", scene, spool=spool, timeout_s=10)
    thread = _answer_with(spool, write)
    with pytest.raises(RenderError, match=message) as err:
        sim.render(0, _texture([0.2, 0.3, 0.4]), 1, 0)
    thread.join(5)
    assert "\n" not in str(err.value) and str(err.value).startswith("sim: unreal: frame 0: ")
    assert not any((spool / "responses").iterdir())


def test_editor_side_errors_reach_undream_as_one_line(scene, spool):
    """A renderer that fails, a render of the wrong size, a request of another version: the worker answers
    with one line (and goes on serving)."""
    sim = make_backend("unreal", scene, spool=spool, timeout_s=10)
    with Editor(spool, RecordedFrames(answer="raise")):
        with pytest.raises(RenderError, match="the editor says: RuntimeError: Movie Render Queue is already"):
            sim.render(0, _texture([0.5, 0.5, 0.5]), 1, 0)
    with Editor(spool, RecordedFrames(answer="small")):
        with pytest.raises(RenderError, match="is 24×15 px"):
            sim.render(0, _texture([0.5, 0.5, 0.5]), 1, 0)
    rid = "future-0001"
    (spool / "requests" / f"{rid}.json").write_text(json.dumps({"format": "undream-unreal-request", "version": 2}))
    with Editor(spool, RecordedFrames()) as editor:
        for _ in range(200):
            if (spool / "responses" / f"{rid}.json").exists():
                break
            time.sleep(0.01)
        assert "version 2" in json.loads((spool / "responses" / f"{rid}.json").read_text())["error"]
        assert editor.worker.busy is None


def test_request_parsing_names_the_field(tmp_path):
    (tmp_path / "t.png").write_bytes(b"png")
    good = {"format": "undream-unreal-request", "version": 1, "id": "a-1", "sequence": "s", "frame": 3,
            "resolution": [64, 32], "spp": 2, "seed": 0, "texture": "t.png"}
    job = rt.parse_request(good, tmp_path)
    assert job.frame == 3 and job.resolution == (64, 32) and job.texture == tmp_path / "t.png"
    for change, message in (({"resolution": [64]}, "resolution"), ({"spp": 0}, "spp"),
                            ({"texture": "../t.png"}, "texture"), ({"texture": "u.png"}, "not found"),
                            ({"id": "a/b"}, "id")):
        with pytest.raises(rt.RequestError, match=message):
            rt.parse_request({**good, **change}, tmp_path)


def test_editor_script_arguments():
    args = rt.parse_args(["--spool", "S:/spool", "--sequence", "/Game/Seq/A", "--material", "/Game/MI"])
    assert args.spool == "S:/spool" and args.format == "exr" and args.parameter == "AdvTexture"
    for bad in (["--sequence", "/Game/A", "--material", "/Game/MI"],
                ["--texture", "t.png", "--sequence", "/Game/A", "--material", "/Game/MI"],
                ["--spool", "s", "--texture", "t.png", "--out", "o", "--sequence", "/Game/A", "--material", "m"]):
        with pytest.raises(SystemExit):
            rt.parse_args(bad)
    assert rt._object_path("/Game/Seq/DriveBy") == "/Game/Seq/DriveBy.DriveBy"


def test_spool_setting_and_run_config(tmp_path):
    from undream.settings import load_local

    cfg = RunConfig(scene="s", sim="unreal")
    assert RunConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    with pytest.raises(SpecError, match="eot.*needs sim: mitsuba"):
        RunConfig(scene="s", sim="unreal", eot={"camera_shift_m": 0.1})
    with pytest.raises(RenderError, match="set UNDREAM_UNREAL_SPOOL"):
        check_simulator("unreal", load_local({}))
    with pytest.raises(RenderError, match="spool folder .*missing not found"):
        check_simulator("unreal", load_local({"UNDREAM_UNREAL_SPOOL": str(tmp_path / "missing")}))
    check_simulator("unreal", load_local({"UNDREAM_UNREAL_SPOOL": str(tmp_path)}))


def test_cli_run_without_spool_writes_nothing(tmp_path):
    """``sim: unreal`` with no spool folder: one line naming the run file, exit 2, --out not created."""
    run = tmp_path / "run.yaml"
    run.write_text(yaml.safe_dump({"scene": str(ROOT / "examples" / "bin_park.yaml"), "sim": "unreal",
                                   "attack": {"name": "pgd", "eps": 8, "steps": 1}}))
    env = {k: v for k, v in os.environ.items() if k != "UNDREAM_UNREAL_SPOOL"}
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(run), "--out", str(tmp_path / "out"),
                          "--no-progress"], capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert "run.yaml" in lines[0] and "UNDREAM_UNREAL_SPOOL" in lines[0]
    assert not (tmp_path / "out").exists()


def test_attack_run_with_unreal_frames(tmp_path, spool, monkeypatch, mi):
    """``sim: unreal`` end to end through ``undream run``'s engine: every attack and evaluation frame is
    a request the stand-in editor answers; the gradient still comes from Mitsuba's gradient scene."""
    from farm_support import make_victim
    from scheduler.local import run_local
    from undream.scene.poses import look_at
    from undream.scenedir.init import InitOptions, init_scene

    frames = tuple(Frame(i, Camera(Transform.from_rows(look_at([1.4 * np.sin(a), 1.0, 2.2 * np.cos(a)],
                                                               [0, 0.5, 0])), 40.0, (W, H)), Transform.identity())
                   for i, a in enumerate([0.0, 0.4, 0.8]))
    seq = Sequence("street", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    scene = init_scene(seq, tmp_path / "scene", InitOptions(verify_spp=1))
    cfg = RunConfig(scene=str(scene), name="ue", victim=make_victim(tmp_path / "victim"), loss="ce", sim="unreal",
                    attack={"name": "pgd", "eps": 32.0, "steps": 2}, sim_spp=2, grad_spp=2, eval_spp=2, seed=1,
                    holdout="none")
    from undream.settings import load_local

    renderer = RecordedFrames()
    with Editor(spool, renderer):
        res = run_local(cfg, tmp_path / "out", progress=False,
                        local=load_local({"UNDREAM_UNREAL_SPOOL": str(spool)}))
    meta = json.loads((tmp_path / "out" / "metadata.json").read_text())
    assert meta["versions"]["simulator"] == "unreal" and meta["versions"]["unreal"] == "5.4.4-fake"
    assert len(res["loss_per_iteration"]) == 2 and all(np.isfinite(res["loss_per_iteration"]))
    assert sorted({j.frame for j in renderer.jobs}) == [0, 1, 2] and len(renderer.jobs) >= 3 * 2 + 3
    assert len(list((tmp_path / "out" / "frames_adversarial").glob("*.png"))) == 3


def test_bad_timeout_is_one_line(scene, spool):
    from undream.settings import SettingsError, load_local

    with pytest.raises(SettingsError, match="UNDREAM_UNREAL_TIMEOUT.*must be a number of seconds > 0, got 'soon'"):
        load_local({"UNDREAM_UNREAL_TIMEOUT": "soon"})
    assert load_local({"UNDREAM_UNREAL_TIMEOUT": "7.5"}).unreal_timeout_s == 7.5
    with pytest.raises(RenderError, match="timeout_s.*got 'soon'"):
        make_backend("unreal", scene, spool=spool, timeout_s="soon")
    with pytest.raises(RenderError, match="got -1"):
        make_backend("unreal", scene, spool=spool, timeout_s=-1)


def test_two_editors_share_a_spool(scene, spool):
    """Each request is claimed by exactly one worker (a rename), so several editors may serve one spool."""
    first, second = RecordedFrames(), RecordedFrames()
    sim = make_backend("unreal", scene, spool=spool, timeout_s=20)
    with Editor(spool, first), Editor(spool, second):
        for k in range(6):
            sim.render(k % 3, _texture([0.1 * k, 0.5, 0.5]), 1, k)
    ids = [j.id for j in first.jobs + second.jobs]
    assert len(ids) == 6 and len(set(ids)) == 6
