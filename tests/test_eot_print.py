"""Print-and-capture EOT (issue 44): seeded per-frame draws, the texture's print and the camera's
noise, and the gradient carried back through them in the real frame job."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from farm_support import make_scene, make_victim
from undream.attacks.print_capture import (
    PrintDraw, capture_noise, draw_print, print_texture, printed, texture_vjp,
)
from undream.errors import SpecError
from undream.spec.physical import PrintEotConfig
from undream.spec.run import RunConfig

FULL = PrintEotConfig(brightness=0.1, contrast=0.2, saturation=0.3, gamma=0.2, blur=1.5, noise=0.02)


def _texture(h: int = 6, w: int = 7, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.1, 0.9, (h, w, 3))


# -- draws ----------------------------------------------------------------------------------------

def test_draws_repeat_from_the_seed_and_differ_between_iterations_and_frames():
    a = draw_print(FULL, 5, 3, 2)
    assert a == draw_print(FULL, 5, 3, 2)  # any process, any retry
    others = [draw_print(FULL, 5, 4, 2), draw_print(FULL, 5, 3, 1), draw_print(FULL, 6, 3, 2)]
    assert all(o != a for o in others) and len({o.noise_seed for o in others + [a]}) == 4
    assert draw_print(None, 5, 3, 2) is None


def test_draws_stay_within_their_bounds():
    draws = [draw_print(FULL, 0, k, f) for k in range(20) for f in range(5)]
    assert all(abs(d.brightness) <= 0.1 and abs(d.contrast - 1) <= 0.2 and abs(d.saturation - 1) <= 0.3
               and np.exp(-0.2) <= d.gamma <= np.exp(0.2) and 0 <= d.blur <= 1.5 and d.noise == 0.02 for d in draws)
    assert np.std([d.brightness for d in draws]) > 0.03  # they do vary
    neutral = draw_print(PrintEotConfig(), 0, 0, 0)
    assert not neutral.changes_texture and neutral.noise == 0.0


def test_bad_eot_print_blocks_are_one_line():
    with pytest.raises(SpecError, match=r"eot_print\.blur: must be in \[0, 16\] \(texels \(Gaussian sigma\)\), got -1"):
        RunConfig.from_json({"scene": "s", "eot_print": {"blur": -1}})
    with pytest.raises(SpecError, match=r"eot_print\.hue: unknown field"):
        RunConfig.from_json({"scene": "s", "eot_print": {"hue": 0.1}})
    cfg = RunConfig.from_json({"scene": "s", "eot_print": {"noise": 0.05, "blur": 2}})
    assert RunConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg
    assert cfg.to_json()["eot_print"] == {**PrintEotConfig().to_json(), "noise": 0.05, "blur": 2.0}


# -- the print and the capture ---------------------------------------------------------------------

def test_known_answers_of_the_print():
    T = torch.from_numpy(_texture())
    assert torch.allclose(print_texture(T, PrintDraw()), T, rtol=0, atol=1e-15)
    assert torch.allclose(print_texture(T, PrintDraw(brightness=0.05)), (T + 0.05).clamp(0, 1))
    grey = print_texture(T, PrintDraw(saturation=0.0))
    assert torch.allclose(grey[..., 0], grey[..., 1]) and torch.allclose(grey[..., 1], grey[..., 2])
    flat = torch.full((5, 5, 3), 0.4, dtype=torch.float64)
    assert torch.allclose(print_texture(flat, PrintDraw(blur=2.0)), flat)  # a blur keeps a flat print
    assert torch.allclose(print_texture(T, PrintDraw(gamma=2.0)), T ** 2)
    x = _texture()
    assert printed(x, None) is x and printed(x, PrintDraw()) is x


def test_the_gradient_through_the_print_matches_finite_differences():
    draw = draw_print(FULL, 5, 1, 0)
    assert draw.changes_texture and draw.blur > 0
    T = torch.from_numpy(_texture(5, 6, seed=3)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: print_texture(x, draw), (T,), eps=1e-6, atol=1e-6, rtol=1e-4)
    g = np.random.default_rng(4).normal(size=(5, 6, 3))
    vjp = texture_vjp(T.detach().numpy(), draw, g)
    i, eps = (2, 3, 1), 1e-6
    up, down = T.detach().numpy().copy(), T.detach().numpy().copy()
    up[i] += eps
    down[i] -= eps
    def inner(x: np.ndarray) -> float:  # <g, print(x)> in float64
        return float(np.sum(g * print_texture(torch.from_numpy(x), draw).numpy()))

    fd = (inner(up) - inner(down)) / (2 * eps)
    assert vjp[i] == pytest.approx(fd, rel=1e-4, abs=1e-6)  # vjp is float32


def test_camera_noise_repeats_and_its_clip_blocks_the_gradient():
    draw = dataclasses.replace(draw_print(FULL, 5, 1, 0), noise=0.2)
    img = np.random.default_rng(0).uniform(0, 1, (8, 9, 3)).astype(np.float32)
    noisy, inside = capture_noise(img, draw)
    again, _ = capture_noise(img, draw)
    assert np.array_equal(noisy, again) and noisy.dtype == np.float32
    assert 0.15 < float(np.std(noisy - img)) < 0.25 and noisy.min() >= 0 and noisy.max() <= 1
    assert inside.dtype == bool and (~inside).any()
    assert np.array_equal(~inside, (noisy == 0) | (noisy == 1))
    assert capture_noise(img, PrintDraw()) == (img, None)


# -- the real frame job and run --------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    base = tmp_path_factory.mktemp("eotp")
    return make_scene(base / "scene", n_frames=2, size=24), make_victim(base / "victim")


def _config(tiny, name="eotp", **extra):
    scene, victim = tiny
    return RunConfig(scene=str(scene), name=name, victim=victim, loss="ce",
                     attack={"name": "pgd", "eps": 32.0, "steps": 2}, sim_spp=2, grad_spp=2, eval_spp=2, seed=5,
                     holdout="none", **extra)


def test_the_frame_job_renders_the_print_and_chains_its_gradient(tiny):
    from undream.engine import job
    from undream.engine.algorithm import start_texture
    from undream.engine.context import build_context

    eot = PrintEotConfig(brightness=0.1, contrast=0.2, saturation=0.3, gamma=0.2, blur=1.0)  # no noise
    ctx = build_context(_config(tiny, eot_print=eot), tiny[0])
    plain = build_context(_config(tiny), tiny[0], victim=ctx.victim)
    T = start_texture(ctx)
    T = np.clip(T + np.random.default_rng(1).uniform(-0.2, 0.2, T.shape), 0, 1).astype(np.float32)
    k = 1
    (res,) = job.render_and_grad_many(ctx, [0], T, k)
    draw = draw_print(eot, 5, k, ctx.frame_indices[0])
    (ref,) = job.render_and_grad_many(plain, [0], printed(T, draw), k)  # the print rendered plainly
    expected = texture_vjp(T, draw, ref.grad)
    assert res.loss == pytest.approx(ref.loss, rel=1e-4)
    scale = float(np.abs(expected).max())
    assert scale > 0 and np.abs(res.grad - expected).max() <= 1e-3 * scale
    assert np.abs(res.grad - ref.grad).max() > 1e-2 * scale  # the chain rule did something


def test_a_run_with_print_eot_is_judged_on_the_plain_texture(tiny, tmp_path):
    from scheduler.local import run_local

    plain = run_local(_config(tiny), tmp_path / "plain", progress=False)
    eot = run_local(_config(tiny, eot_print=FULL.to_json()), tmp_path / "eot", progress=False)
    assert eot["benign"] == plain["benign"]  # the evaluation sees no training draw
    assert eot["loss_per_iteration"] != plain["loss_per_iteration"]
    assert not np.array_equal(np.load(tmp_path / "eot" / "texture_final.npy"),
                              np.load(tmp_path / "plain" / "texture_final.npy"))
    again = run_local(_config(tiny, eot_print=FULL.to_json(), name="again"), tmp_path / "again", progress=False)
    assert again["loss_per_iteration"] == pytest.approx(eot["loss_per_iteration"], rel=1e-5)


def test_undream_evaluate_judges_under_print_capture_draws_no_attack_made(tiny, tmp_path):
    from click.testing import CliRunner

    from undream.cli import main

    scene, victim = tiny
    np.save(tmp_path / "t.npy", np.random.default_rng(0).uniform(0, 1, (8, 16, 3)).astype(np.float32))

    def evaluate(*extra):
        res = CliRunner().invoke(main, ["evaluate", str(tmp_path / "t.npy"), str(scene), "--victim", victim,
                                        "--spp", "2", "--holdout", "none", *extra], env={"HF_HUB_OFFLINE": "1"})
        return res

    def scores(name):
        doc = json.loads((tmp_path / name).read_text())
        return doc, [(f["benign_score"], f["texture_score"]) for f in doc["frames"]]

    capture = "{brightness: 0.2, contrast: 0.3, gamma: 0.3, blur: 2, noise: 0.05}"
    for name, extra in (("plain.json", ()), ("cap.json", ("--print-capture", capture)),
                        ("again.json", ("--print-capture", capture))):
        res = evaluate(*extra, "--json", str(tmp_path / name))
        assert res.exit_code == 0, res.output
    plain, plain_scores = scores("plain.json")
    cap, cap_scores = scores("cap.json")
    assert "print_capture" not in plain and cap["print_capture"]["blur"] == 2.0
    assert cap_scores == scores("again.json")[1]  # the evaluation's draws repeat
    assert all(p != c for p, c in zip(plain_scores, cap_scores))  # and change every frame, benign and adversarial
    res = evaluate("--print-capture", "{blur: 99}")
    lines = [line for line in res.output.strip().splitlines() if line]
    assert res.exit_code == 2 and len(lines) == 1 and "eot_print.blur: must be in [0, 16]" in lines[0], res.output
