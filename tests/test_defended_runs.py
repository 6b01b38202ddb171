"""Defended victims on the path a run takes (issue 45): `undream run` builds its victim behind the
run's defence (undream.engine.context.build_context, which the farm's workers call too), the attack
differentiates through it or, non-adaptive, around it, the evaluation always judges through it;
`undream evaluate --defence`; bad settings one line, nothing written."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from farm_support import make_scene, make_victim
from undream.errors import SpecError
from undream.spec.run import RunConfig
from undream.victims import Classifier
from undream.victims import defended

LEVELS = np.array([0.0, 1 / 3, 2 / 3, 1.0])  # bits: 2


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    base = tmp_path_factory.mktemp("defended")
    return make_scene(base / "scene", n_frames=2, size=24), make_victim(base / "victim")


def _config(tiny, defence, name="defended", steps=2):
    scene, victim = tiny
    return RunConfig(scene=str(scene), name=name, victim=victim, loss="ce",
                     attack={"name": "pgd", "eps": 32.0, "steps": steps}, sim_spp=2, grad_spp=2, eval_spp=2,
                     seed=5, holdout="none", defence=defence)


@pytest.fixture
def seen(monkeypatch):
    """Every batch the (inner) model was given: (images, whether they carry a gradient)."""
    calls = []
    forward = Classifier.forward_raw

    def spy(self, images):
        calls.append((images.detach().numpy().copy(), images.requires_grad))
        return forward(self, images)

    monkeypatch.setattr(Classifier, "forward_raw", spy)
    return calls


def _on_levels(images: np.ndarray) -> bool:
    return bool(np.abs(images[..., None] - LEVELS).min(-1).max() < 1e-6)


def test_the_run_attacks_and_judges_through_the_defence(tiny, tmp_path, seen):
    from scheduler.local import run_local

    results = run_local(_config(tiny, {"bits": 2}), tmp_path / "run", progress=False)
    attack = [im for im, grad in seen if grad]
    judged = [im for im, grad in seen if not grad]
    assert len(attack) == 2 and judged  # 2 steps of one batch of 2 frames; then the evaluation
    assert all(_on_levels(im) for im in attack + judged)  # every frame the model saw was reduced to 2 bits
    assert len(results["loss_per_iteration"]) == 2
    assert results["defence"] == {"steps": [{"bits": 2}], "backward": "auto", "adaptive": True, "draws": 1}
    meta = json.loads((tmp_path / "run" / "metadata.json").read_text())
    assert meta["config"]["defence"]["steps"] == [{"bits": 2}]


def test_a_non_adaptive_attack_ignores_the_defence_the_evaluation_does_not(tiny, tmp_path, seen):
    from scheduler.local import run_local

    results = run_local(_config(tiny, {"bits": 2, "adaptive": False}, name="blind"), tmp_path / "run", progress=False)
    assert results["defence"]["adaptive"] is False
    attack = [im for im, grad in seen if grad]
    judged = [im for im, grad in seen if not grad]
    assert len(attack) == 2 and not any(_on_levels(im) for im in attack)  # the undefended victim's frames
    assert judged and all(_on_levels(im) for im in judged)


def test_random_defences_draw_per_run_seed_iteration_and_frame(tiny, tmp_path, seen, monkeypatch):
    from scheduler.local import run_local
    from undream.victims.defences import CONTENT_ITERATION

    keys = []
    draw = defended.draw_resize_pad

    def spy(step, key, h, w):
        keys.append(key)
        return draw(step, key, h, w)

    monkeypatch.setattr(defended, "draw_resize_pad", spy)
    defence = {"resize_pad": {"scale": [0.7, 1.0], "pad": 0.25}, "draws": 2}
    first = run_local(_config(tiny, defence, name="rp"), tmp_path / "a", progress=False)
    attack = {k[:3] for k in keys if k[1] != CONTENT_ITERATION}
    assert attack == {(5, k, f) for k in (0, 1) for f in (0, 1)}  # (seed, iteration, frame index)
    assert {k[3] for k in keys if k[1] != CONTENT_ITERATION} == {0, 1}  # two EOT draws each
    assert any(k[1] == CONTENT_ITERATION for k in keys)  # the evaluation: drawn from each frame's content
    assert {im.shape[1:] for im, _ in seen} == {(3, 30, 30)}  # the 24 px frames on a 1.25× canvas
    again = run_local(_config(tiny, defence, name="rp2"), tmp_path / "b", progress=False)
    assert again["loss_per_iteration"] == pytest.approx(first["loss_per_iteration"], rel=1e-5)
    assert again["adversarial"] == first["adversarial"]


def test_undream_evaluate_judges_through_a_defence(tiny, tmp_path, seen):
    from undream.cli import main

    scene, victim = tiny
    np.save(tmp_path / "t.npy", np.random.default_rng(0).uniform(0, 1, (8, 16, 3)).astype(np.float32))
    res = CliRunner().invoke(main, ["evaluate", str(tmp_path / "t.npy"), str(scene), "--victim", victim, "--spp", "2",
                                    "--holdout", "none", "--defence", "{bits: 2}", "--json", str(tmp_path / "e.json")],
                             env={"HF_HUB_OFFLINE": "1"})
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["defence"]["steps"] == [{"bits": 2}]
    assert {row["victim"] for row in doc["rows"]} == {f"{victim} + bits 2"}
    assert seen and all(_on_levels(im) for im, _ in seen)
    bad = CliRunner().invoke(main, ["evaluate", str(tmp_path / "t.npy"), str(scene), "--victim", victim,
                                    "--defence", "{jpeg: 101}"], env={"HF_HUB_OFFLINE": "1"})
    lines = [line for line in bad.output.strip().splitlines() if line]
    assert bad.exit_code == 2 and len(lines) == 1, bad.output
    assert "defence.steps[0].jpeg: must be a JPEG quality, an integer in 1..100, got 101" in lines[0]


@pytest.mark.parametrize("defence, needle", [
    ({"median": 2}, "defence.steps[0].median: must be an odd kernel size"),
    ({"jpeg": 75, "backward": "exact"}, "defence.backward: cannot differentiate jpeg exactly"),
    ({"sharpen": 1}, "defence.sharpen: unknown"),
])
def test_undream_run_refuses_a_bad_defence_in_one_line_writing_nothing(tiny, tmp_path, defence, needle):
    from undream.cli import main

    scene, victim = tiny
    spec = tmp_path / "run.yaml"
    spec.write_text(yaml.safe_dump({"scene": str(scene), "victim": victim, "defence": defence}))
    res = CliRunner().invoke(main, ["run", str(spec), "--out", str(tmp_path / "out"), "--no-progress"],
                             env={"HF_HUB_OFFLINE": "1"})
    lines = [line for line in res.output.strip().splitlines() if line]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert "run.yaml" in lines[0] and needle in lines[0]
    assert not (tmp_path / "out").exists()


def test_the_farm_judges_and_attacks_through_the_defence_like_a_local_run(tiny, tmp_path, seen):
    from farm_support import eager_run
    from scheduler.local import run_local

    defence = {"steps": [{"resize_pad": {"scale": [0.7, 1.0], "pad": 0.25}}, {"bits": 2}]}
    cfg = _config(tiny, defence, name="farm-defended")
    local = run_local(cfg, tmp_path / "local", progress=False)
    n_local = len(seen)
    store, run_id = eager_run(cfg, tmp_path)
    try:
        run = store.get_run(run_id)
        assert run.status == "done", run.error
        farm = seen[n_local:]
        assert any(grad for _, grad in farm) and any(not grad for _, grad in farm)
        assert all(im.shape[1:] == (3, 30, 30) and _on_levels(im) for im, _ in farm)  # the workers' frames defended
        assert run.run_config.defence == cfg.defence
        assert [it.loss_mean for it in store.iterations(run_id)] == pytest.approx(local["loss_per_iteration"], rel=1e-5)
        assert np.array_equal(np.load(tmp_path / "out" / "texture_final.npy"),
                              np.load(tmp_path / "local" / "texture_final.npy"))
    finally:
        store.close()


@pytest.mark.parametrize("step", [{"jpeg": 40}, {"median": 3}, {"gaussian": 1.0}, {"bits": 3}])
def test_each_defence_transforms_the_frames_of_the_frame_job_and_the_evaluation(tiny, seen, step):
    import torch

    from undream.engine import job
    from undream.engine.algorithm import eval_predictions, eval_render, start_texture
    from undream.engine.context import build_context
    from undream.spec.defence import DefenceStep
    from undream.victims.defences import forward

    plain = build_context(_config(tiny, None), tiny[0])
    ctx = build_context(_config(tiny, step), tiny[0], victim=plain.victim)
    assert isinstance(ctx.victim, defended.DefendedVictim) and ctx.victim.inner is plain.victim
    T = start_texture(ctx)
    for c in (plain, ctx):
        job.render_and_grad_many(c, [0, 1], T, 1)
        eval_predictions(c, [eval_render(c, p, T) for p in (0, 1)])
    assert [grad for _, grad in seen] == [True, False, True, False]
    (raw, _), (raw_eval, _), (got, _), (got_eval, _) = seen
    transform = DefenceStep.from_json(step)
    for frames, defended_frames in ((raw, got), (raw_eval, got_eval)):
        expected = forward(transform, torch.from_numpy(frames)).numpy()
        assert np.allclose(defended_frames, expected, atol=1e-6)
        assert not np.allclose(defended_frames, frames, atol=1e-3)
    plain.scenes.close()
    ctx.scenes.close()


def test_a_sweep_grids_defences_and_their_options(tiny, tmp_path):
    from scheduler.sweep import load_sweep

    scene, victim = tiny
    base = {"scene": str(scene), "victim": victim, "defence": {"jpeg": 75}}
    (tmp_path / "a.yaml").write_text(yaml.safe_dump({"name": "d", "base": base, "grid": {
        "defence.adaptive": [False, True], "defence.backward": ["auto", "smooth"]}}))
    runs = load_sweep(tmp_path / "a.yaml").runs
    assert [(r.config.defence.adaptive, r.config.defence.backward) for r in runs] == [
        (False, "auto"), (False, "smooth"), (True, "auto"), (True, "smooth")]
    (tmp_path / "b.yaml").write_text(yaml.safe_dump({"name": "e", "base": {**base, "defence": None}, "grid": {
        "defence": [None, {"median": 3}, [{"gaussian": 1.0}, {"bits": 5}]]}}))
    assert [r.config.defence and r.config.defence.label for r in load_sweep(tmp_path / "b.yaml").runs] == [
        None, "median 3", "gaussian 1 + bits 5"]
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"name": "f", "base": base, "grid": {"defence.draws": [2]}}))
    with pytest.raises(SpecError, match=r"defence\.draws: must be 1 without a random defence"):
        load_sweep(tmp_path / "c.yaml")
