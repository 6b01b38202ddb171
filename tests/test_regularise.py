"""The objective's regularisers (issue 44): TV, non-printability and camouflage, their palettes in
the run config, and a real run that records them per iteration and is smoothed by them."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from farm_support import make_scene, make_victim, write_yaml
from undream.attacks.regularise import (
    SMOOTH, Regularisers, camouflage, non_printability, objective, palette_distance, palette_tensor, smooth_abs,
    total_variation,
)
from undream.errors import AttackError, SpecError
from undream.spec.physical import BUILTIN_PALETTES, RegulariseConfig, read_palette
from undream.spec.run import RunConfig, load_run_config


def _texture(h: int = 5, w: int = 6, seed: int = 0) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).uniform(0.05, 0.95, (h, w, 3)))


PALETTE = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.8, 0.2, 0.1], [0.1, 0.5, 0.9]], dtype=torch.float64)


# -- known answers -------------------------------------------------------------------------------

def test_tv_of_a_constant_texture_is_zero_and_of_stripes_the_mean_step():
    assert float(total_variation(torch.full((4, 7, 3), 0.3, dtype=torch.float64))) == 0.0
    stripes = torch.zeros((4, 6, 3), dtype=torch.float64)
    stripes[:, 1::2] = 0.5  # every horizontal step is 0.5, every vertical step 0
    expected = float(smooth_abs(torch.tensor(0.5, dtype=torch.float64)))
    assert float(total_variation(stripes)) == pytest.approx(expected, abs=1e-12)
    assert expected == pytest.approx(0.5, abs=SMOOTH)


def test_nps_of_palette_colours_is_zero_and_grows_with_the_distance():
    on = PALETTE[torch.tensor([[0, 1], [2, 3]])]  # a 2×2 texture of palette colours
    assert float(non_printability(on, PALETTE)) == 0.0
    off = on.clone()
    off[0, 0] = torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)  # 0.3 from black, every other texel on the palette
    d = float(torch.sqrt(torch.tensor(0.09 + SMOOTH**2, dtype=torch.float64)) - SMOOTH)
    assert float(non_printability(off, PALETTE)) == pytest.approx(d / 4, abs=1e-12)


def test_camouflage_is_the_distance_to_the_background_palette():
    background = torch.tensor([[0.2, 0.4, 0.1]], dtype=torch.float64)
    T = _texture()
    assert float(camouflage(T, background)) == pytest.approx(float(palette_distance(T, background)))
    near = background.reshape(1, 1, 3).expand(3, 3, 3).clone()
    assert float(camouflage(near, background)) == 0.0


def test_the_class_agrees_with_the_functions():
    cfg = RegulariseConfig(tv=2.0, nps=0.5, camouflage=3.0, palette_rgb=(PALETTE * 255).tolist(),
                           background_rgb=[[51, 102, 25.5]])
    regs = Regularisers.of(cfg)
    T = _texture()
    total, values = regs(T)
    bg = palette_tensor([[51, 102, 25.5]])
    assert values == pytest.approx({"tv": float(total_variation(T)), "nps": float(non_printability(T, PALETTE)),
                                    "camouflage": float(camouflage(T, bg))})
    assert float(total) == pytest.approx(2.0 * values["tv"] + 0.5 * values["nps"] + 3.0 * values["camouflage"])
    assert Regularisers.of(None) is None and Regularisers.of(RegulariseConfig()) is None


# -- gradients ------------------------------------------------------------------------------------

@pytest.mark.parametrize("term", ["tv", "nps", "camouflage"])
def test_gradients_match_finite_differences(term):
    T = _texture(4, 5, seed=1).requires_grad_(True)
    fn = {"tv": lambda x: total_variation(x), "nps": lambda x: non_printability(x, PALETTE),
          "camouflage": lambda x: camouflage(x, PALETTE[2:])}[term]
    assert torch.autograd.gradcheck(fn, (T,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_the_gradient_at_zero_is_zero_not_undefined():
    T = torch.full((3, 3, 3), 0.5, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(total_variation(T), T)
    assert torch.equal(g, torch.zeros_like(g))
    P = PALETTE[1:2].reshape(1, 1, 3).expand(2, 2, 3).clone().requires_grad_(True)
    (g,) = torch.autograd.grad(non_printability(P, PALETTE), P)
    assert torch.isfinite(g).all() and float(g.abs().max()) == 0.0


def test_the_objective_subtracts_the_weighted_terms_on_seen_texels_only():
    cfg = RegulariseConfig(tv=10.0, nps=1.0, palette_rgb=(PALETTE * 255).tolist())
    regs = Regularisers.of(cfg)
    T = _texture(4, 4, seed=2)
    grad = torch.zeros((4, 4, 3), dtype=torch.float32)
    grad[0, 0] = 0.5  # the victim's gradient reaches texel (0, 0) only
    seen = torch.zeros((4, 4), dtype=torch.bool)
    seen[1, 1] = True  # and the attack has seen (1, 1) before
    G, value, record = objective(regs, T.numpy(), grad, 2.0, seen)
    Tg = T.clone().requires_grad_(True)
    (g_reg,) = torch.autograd.grad(regs(Tg)[0], Tg)
    mask = torch.zeros((4, 4, 1), dtype=torch.bool)
    mask[0, 0] = mask[1, 1] = True
    assert torch.allclose(G.double(), torch.where(mask, grad.double() - g_reg, torch.zeros_like(g_reg)), atol=1e-6)
    assert value == pytest.approx(2.0 - 10.0 * record["reg_tv"] - record["reg_nps"])
    assert record["loss_victim"] == 2.0 and record["loss_total"] == value and set(record) == {
        "loss_victim", "loss_total", "reg_tv", "reg_nps"}
    same = objective(None, T.numpy(), grad, 2.0, seen)
    assert same[0] is grad and same[1:] == (2.0, {})


def test_bad_textures_and_palettes_are_attack_errors():
    with pytest.raises(AttackError, match=r"T: must be an H×W×3"):
        total_variation(torch.zeros((4, 4)))
    with pytest.raises(AttackError, match=r"palette: must be an N×3"):
        non_printability(_texture(), torch.zeros((0, 3)))


# -- palettes in the run config -------------------------------------------------------------------

def test_the_shipped_palette_is_documented_and_in_range():
    text = BUILTIN_PALETTES["printable"].read_text()
    assert "Artifex CMYK SWOP Profile" in text and "libgs-common" in text
    colours = read_palette("palette", "printable")
    assert len(colours) >= 100 and all(0 <= v <= 255 for rgb in colours for v in rgb)
    assert (255.0, 255.0, 255.0) in colours  # paper white


def test_a_user_palette_is_read_into_the_config_and_round_trips(tmp_path):
    (tmp_path / "pal.csv").write_text("# measured from our printed chart\nr,g,b\n0,0,0\n255, 128, 0.5\n10;20;30\n")
    run = write_yaml(tmp_path / "run.yaml", {"scene": "scene", "regularise": {"nps": 0.1, "palette": "pal.csv"}})
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "sequence.json").write_text("{}")
    cfg = load_run_config(run)  # the palette beside the run file, not in the working directory
    assert cfg.regularise.palette_rgb == ((0, 0, 0), (255, 128, 0.5), (10, 20, 30))
    again = RunConfig.from_json(json.loads(json.dumps(cfg.to_json())))
    assert again == cfg
    (tmp_path / "pal.csv").unlink()  # a stored config needs no file: it holds the colours
    stored = RunConfig.from_json(json.loads(json.dumps(cfg.to_json())))
    assert stored.regularise.palette_rgb == cfg.regularise.palette_rgb


@pytest.mark.parametrize("text, message", [
    (None, r"regularise\.palette: .*pal\.csv: file not found"),
    ("r,g,b\n1,2\n", r"regularise\.palette: .*pal\.csv line 2: expected 3 numbers r,g,b \(sRGB, 0-255\), got '1,2'"),
    ("1,2,3,4\n", r"line 1: expected 3 numbers"),
    ("0,0,0\n1,2,x\n", r"line 2: expected 3 numbers"),
    ("0,0,256\n", r"regularise\.palette: .*pal\.csv line 1: values must be sRGB in 0-255, got '0,0,256'"),
    ("0,-1,0\n", r"line 1: values must be sRGB in 0-255"),
    ("# nothing\nr,g,b\n", r"regularise\.palette: .*pal\.csv: no colours"),
    ("", r"no colours"),
])
def test_a_bad_palette_is_one_line_naming_the_file_and_line(tmp_path, text, message):
    if text is not None:
        (tmp_path / "pal.csv").write_text(text)
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "sequence.json").write_text("{}")
    run = write_yaml(tmp_path / "run.yaml", {"scene": "scene", "regularise": {"nps": 1.0, "palette": "pal.csv"}})
    with pytest.raises(SpecError, match=message) as err:
        load_run_config(run)
    assert "\n" not in str(err.value) and str(err.value).startswith(str(run))


@pytest.mark.parametrize("block, message", [
    ({"tv": -1}, r"regularise\.tv: must be a weight in \[0, 1e\+06\], got -1"),
    ({"nps": "a lot"}, r"regularise\.nps: must be a number, got 'a lot'"),
    ({"camouflage": 1.0}, r"regularise\.camouflage: needs background"),
    ({"smooth": 1.0}, r"regularise\.smooth: unknown field"),
    ({"nps": 1, "palette_rgb": [[0, 0, 300]]}, r"regularise\.palette_rgb\[0\]: must be an sRGB colour in 0-255"),
    ({"nps": 1, "palette_rgb": []}, r"regularise\.palette_rgb: must be a non-empty list"),
    ([1, 2], r"regularise: must be a mapping"),
])
def test_bad_regularise_blocks_are_one_line(block, message):
    with pytest.raises(SpecError, match=message):
        RunConfig.from_json({"scene": "s", "regularise": block})


def test_an_unweighted_palette_is_not_read():
    cfg = RunConfig.from_json({"scene": "s", "regularise": {"tv": 1.0}})
    assert cfg.regularise.palette_rgb is None and cfg.regularise.background_rgb is None


# -- a real run -----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    base = tmp_path_factory.mktemp("reg")
    return make_scene(base / "scene", n_frames=2, size=24), make_victim(base / "victim")


def _run(tiny, out, attack=None, **extra):
    from scheduler.local import run_local

    scene, victim = tiny
    cfg = RunConfig(scene=str(scene), name="reg", victim=victim, loss="ce",
                    attack=attack or {"name": "pgd", "eps": 32.0, "steps": 2}, sim_spp=2, grad_spp=2, eval_spp=2,
                    seed=5,
                    holdout="none", **extra)
    return run_local(cfg, out, progress=False), np.load(out / "texture_final.npy")


def test_a_run_records_its_terms_and_a_large_tv_weight_smooths_the_texture(tiny, tmp_path):
    plain, T_plain = _run(tiny, tmp_path / "plain")
    smooth, T_smooth = _run(tiny, tmp_path / "smooth", regularise={"tv": 1000.0, "nps": 0.1})
    assert "objective_per_iteration" not in plain
    terms = smooth["objective_per_iteration"]
    assert set(terms) == {"loss_victim", "loss_total", "reg_tv", "reg_nps"} and all(len(v) == 2 for v in terms.values())
    assert terms["loss_victim"] == smooth["loss_per_iteration"]  # loss_mean stays the victim's
    assert terms["loss_total"] == pytest.approx([v - 1000.0 * t - 0.1 * n for v, t, n in
                                                 zip(terms["loss_victim"], terms["reg_tv"], terms["reg_nps"])])
    from undream.store import open_store

    with open_store(None, tmp_path / "smooth" / "store") as store:
        assert [r.terms["reg_tv"] for r in store.iterations(smooth["run_id"])] == terms["reg_tv"]
    tv = {name: float(total_variation(torch.from_numpy(T).double())) for name, T in
          (("plain", T_plain), ("smooth", T_smooth))}
    assert tv["smooth"] < 0.75 * tv["plain"], tv
    assert plain["benign"] == smooth["benign"]  # the regularisers change the attack, not the judge


def test_undream_run_refuses_a_bad_palette_in_one_line_and_writes_nothing(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "sequence.json").write_text("{}")
    (tmp_path / "chart.csv").write_text("r,g,b\n12,40\n")
    run = write_yaml(tmp_path / "run.yaml", {"scene": "scene", "regularise": {"nps": 1.0, "palette": "chart.csv"}})
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(run), "--out", str(tmp_path / "out"),
                          "--no-progress"], capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 2, res.stderr
    line = res.stderr.strip()
    assert "\n" not in line and "regularise.palette" in line and "chart.csv line 2" in line, line
    assert not (tmp_path / "out").exists()


def test_a_sweep_reads_palettes_beside_its_run_file_and_grids_the_weights(tmp_path):
    from scheduler.sweep import load_sweep

    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "chart.csv").write_text("0,0,0\n255,255,255\n")
    write_yaml(tmp_path / "base" / "run.yaml", {"scene": "scene", "regularise": {"nps": 1.0, "palette": "chart.csv"}})
    sweep = load_sweep(write_yaml(tmp_path / "s.yaml", {"name": "g", "run": "base/run.yaml",
                                                        "grid": {"regularise.tv": [0.0, 2.5]}}))
    assert [r.config.regularise.tv for r in sweep.runs] == [0.0, 2.5]
    assert all(r.config.regularise.palette_rgb == ((0, 0, 0), (255, 255, 255)) for r in sweep.runs)


def test_apgds_final_pick_compares_objectives(tiny, tmp_path, monkeypatch):
    """APGD's final pick weighs the last texture by the objective its steps saw, not the victim's loss alone."""
    from undream.attacks.apgd import APGD
    from undream.engine.algorithm import objective_value
    from undream.store import open_store

    cfg = RunConfig.from_json({"scene": "s", "regularise": {"tv": 4.0}})
    T = _texture().numpy()
    assert objective_value(cfg, T, 2.0) == pytest.approx(2.0 - 4.0 * float(total_variation(torch.from_numpy(T))))
    assert objective_value(RunConfig.from_json({"scene": "s"}), T, 2.0) == 2.0
    seen = []
    real = APGD.final
    monkeypatch.setattr(APGD, "final", lambda self, T, loss, state: seen.append((T.numpy().copy(), loss))
                        or real(self, T, loss, state))
    res, T_final = _run(tiny, tmp_path / "apgd", regularise={"tv": 10.0},
                        attack={"name": "apgd", "eps": 32.0, "steps": 2})
    assert len(res["objective_per_iteration"]["reg_tv"]) == 2 and np.isfinite(T_final).all()
    (T_last, loss), = seen
    with open_store(None, tmp_path / "apgd" / "store") as store:
        victim = np.mean([j.result["loss"] for j in store.jobs(res["run_id"], 2, "pre")])
    tv = float(total_variation(torch.from_numpy(T_last).double()))
    assert tv > 0 and loss == pytest.approx(victim - 10.0 * tv, rel=1e-6)


def test_a_run_of_apgd_takes_its_first_step_from_the_config(tiny, tmp_path):
    """``attack.step_size`` reaches APGD on the run's path: its first step moves the seen texels by
    η₀ = 2/255 exactly, where the paper's η₀ = 2ε moves them by 64/255 at ε 32."""
    from undream.store import open_store

    moved = {}
    for name, attack in (("small", {"step_size": 2.0}), ("paper", {})):
        res, _ = _run(tiny, tmp_path / name, regularise={"tv": 10.0},
                      attack={"name": "apgd", "eps": 32.0, "steps": 2, **attack})
        with open_store(None, tmp_path / name / "store") as store:
            step = np.abs(store.texture(res["run_id"], 1) - store.texture(res["run_id"], 0))
        moved[name] = np.round(step[step > 0] * 255, 3)
    assert moved["small"].max() == 2.0 and np.mean(moved["small"] == 2.0) > 0.5, moved["small"]  # less: clipped at 0 or 1
    assert moved["paper"].max() > 8
