"""The attack engine in one process: outputs, determinism, unseen texels, bad gradients, idempotence."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from farm_support import make_victim
from undream.engine.context import build_context
from undream.engine.algorithm import quantise
from undream.engine.job import FrameResult
from scheduler.iteration import AllFramesFailed, reduce_and_step
from undream.scenedir.init import InitOptions, init_scene
from undream.scene.poses import look_at
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.spec.run import RunConfig


@pytest.fixture(scope="module")
def victim_dir(tmp_path_factory):
    """A tiny random HF ResNet over the built-in classes, saved locally (no network)."""
    return make_victim(tmp_path_factory.mktemp("victim") / "tiny")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory, mi):
    frames = tuple(Frame(i, Camera(Transform.from_rows(look_at([1.6 * np.sin(a), 1.2, 2.4 * np.cos(a)], [0, 0.5, 0])),
                                   40.0, (24, 24)), Transform.identity(), Environment("cloudy", 12.0))
                   for i, a in enumerate([0.0, 0.5, 1.0]))
    seq = Sequence("eng", Asset("ball", "builtin:sphere", texture=TextureParam(resolution=(16, 8))), frames)
    return init_scene(seq, tmp_path_factory.mktemp("eng") / "scene", InitOptions(verify_spp=1))


def _config(scene_dir, victim_dir, **attack):
    return RunConfig(scene=str(scene_dir), name="t", victim=victim_dir, loss="ce",
                     attack={"name": "pgd", "eps": 32.0, "steps": 3, **attack},
                     sim_spp=4, grad_spp=4, eval_spp=4, seed=5)


def _run(cfg, out):
    from scheduler.local import run_local
    return run_local(cfg, out, progress=False)


def test_run_writes_every_output_and_is_deterministic(scene_dir, victim_dir, tmp_path):
    cfg = _config(scene_dir, victim_dir)
    res = _run(cfg, tmp_path / "a")
    for name in ("texture_final.png", "texture_final.npy", "results.json", "loss.png", "metadata.json"):
        assert (tmp_path / "a" / name).is_file(), name
    assert len(list((tmp_path / "a" / "frames_benign").glob("*.png"))) == 3
    assert len(list((tmp_path / "a" / "frames_adversarial").glob("*.png"))) == 3
    assert len(res["loss_per_iteration"]) == 3
    assert set(res["wall_time_seconds"]) >= {"sim_render", "victim", "grad_render", "reduce_step", "evaluation"}
    from undream.store import open_store

    with open_store(None, tmp_path / "a" / "store") as store:  # transient blobs: no gradient is left
        run_id = res["run_id"]
        assert store.blobs.listing(f"runs/{run_id}/grad") == [] and len(store.jobs(run_id)) == 9
        assert store.seen_mask(run_id).shape == (8, 16)  # what the dashboard hatches, kept from k = 0
        assert store.blobs.usage(f"runs/{run_id}/eval")[0] == 6  # evaluation frames stay (outputs, report)
    assert res["benign"]["metric"] == "accuracy" and len(res["adversarial"]["per_frame"]) == 3
    again = _run(cfg, tmp_path / "b")
    assert np.array_equal(np.load(tmp_path / "a" / "texture_final.npy"), np.load(tmp_path / "b" / "texture_final.npy"))
    # Dr.Jit accumulates film samples and texture gradients with parallel atomics: the
    # summation order varies, so losses agree to float32 rounding, not bit for bit.
    assert again["loss_per_iteration"] == pytest.approx(res["loss_per_iteration"], rel=1e-5)


def test_unseen_texels_keep_their_value(scene_dir, victim_dir, tmp_path, monkeypatch):
    from undream.store import Store, open_store

    monkeypatch.setattr(Store, "drop_gradients", lambda *a: 0)  # this test reads every iteration's gradients

    res = _run(_config(scene_dir, victim_dir, random_start=True), tmp_path / "r")
    store = open_store(None, tmp_path / "r" / "store")
    from PIL import Image

    seen = np.asarray(Image.open(tmp_path / "r" / "texture_visibility.png")) > 0  # random start moved these
    for k in range(3):
        for _, g, _, _ in store.frame_grads(res["run_id"], k):
            seen |= (g != 0).any(axis=2)
    final = np.load(tmp_path / "r" / "texture_final.npy")
    start = quantise(np.full((8, 16, 3), 0.5, np.float32))
    assert (~seen).sum() > 10, "the test needs texels that no frame sees"
    assert np.array_equal(final[~seen], start[~seen])
    assert not np.array_equal(final[seen], start[seen])


def _fake_job(bad_positions):
    from undream.engine import job

    real = job.render_and_grad_many

    def fake(ctx, positions, texture, iteration):
        out = []
        for position, res in zip(positions, real(ctx, positions, texture, iteration)):
            if position in bad_positions:
                grad = res.grad.copy()
                grad[0, 0, 0] = np.nan
                res = FrameResult(grad, res.loss, False, res.prediction, res.timings)
            out.append(res)
        return out
    return fake


def test_a_nan_frame_is_dropped_with_a_warning(scene_dir, victim_dir, tmp_path, monkeypatch, caplog):
    from undream.engine import job

    monkeypatch.setattr(job, "render_and_grad_many", _fake_job({1}))
    with caplog.at_level(logging.WARNING):
        res = _run(_config(scene_dir, victim_dir), tmp_path / "n")
    assert res["frames_dropped_per_iteration"] == [1, 1, 1]
    assert any("non-finite" in r.message for r in caplog.records)
    assert np.isfinite(np.load(tmp_path / "n" / "texture_final.npy")).all()


def test_all_frames_bad_fails_the_run_clearly(scene_dir, victim_dir, tmp_path, monkeypatch):
    from undream.engine import job
    from undream.store import open_store

    monkeypatch.setattr(job, "render_and_grad_many", _fake_job({0, 1, 2}))
    with pytest.raises(AllFramesFailed, match="all 3 frames gave a non-finite gradient"):
        _run(_config(scene_dir, victim_dir), tmp_path / "f")
    store = open_store(None, tmp_path / "f" / "store")
    runs = store.runs()
    assert runs[0].status == "failed" and "non-finite" in runs[0].error


def test_reduce_and_step_is_idempotent(scene_dir, victim_dir, tmp_path):
    from undream.attacks import state_to_dict
    from undream.engine.job import render_and_grad
    from undream.store import open_store

    cfg = _config(scene_dir, victim_dir)
    ctx = build_context(cfg, scene_dir)
    store = open_store(None, tmp_path / "store")
    T0, state = ctx.attack.start(torch.full((8, 16, 3), 0.5), visible=torch.zeros(8, 16, dtype=torch.bool))
    run = store.create_run("t", cfg.to_json(), 3, 5, T0.numpy(), state_to_dict(state))
    for pos in range(3):
        store.job_started(run, 0, pos)
        r = render_and_grad(ctx, pos, T0.numpy(), 0)
        store.job_succeeded(run, 0, pos, r.grad, r.loss, r.finite, r.timings)
    assert reduce_and_step(store, ctx.attack, run, 0) is True
    assert reduce_and_step(store, ctx.attack, run, 0) is False
    assert store.get_run(run).iteration == 1 and len(store.iterations(run)) == 1
