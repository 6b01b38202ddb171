"""Batched frames: a job's frames share one victim pass, and nothing else about the run changes.

The victim runs once per batch of frames (``victim_batch``), forward and
backward, in the attack and in the evaluation. Each frame keeps its own
record (loss, prediction, gradient, finite flag), its texture gradient equals
the one of the frame computed alone to float rounding, and a run batched by 1
ends with the same final texture as a run batched by the whole sequence.
"""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from farm_support import make_scene, make_victim
from undream.engine.algorithm import frame_job, frame_jobs, start_texture
from undream.engine.context import build_context
from undream.spec.run import RunConfig
from undream.victims.classifier import Classifier

N_FRAMES = 4


@pytest.fixture(scope="module")
def victim_dir(tmp_path_factory):
    return make_victim(tmp_path_factory.mktemp("victim") / "tiny")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory, mi):
    return make_scene(tmp_path_factory.mktemp("batch") / "scene", N_FRAMES)


def _config(scene_dir, victim_dir, **extra):
    fields = {"attack": {"name": "pgd", "eps": 32.0, "steps": 3}, **extra}
    return RunConfig(scene=str(scene_dir), name="b", victim=victim_dir, loss="ce", holdout="none",
                     sim_spp=4, grad_spp=4, eval_spp=4, seed=3, **fields)


@pytest.fixture
def victim_calls(monkeypatch):
    """The batch size of every call of a classifier's model, in order."""
    calls: list[int] = []
    forward = Classifier.forward_raw

    def counted(self, images):
        calls.append(int(images.shape[0]))
        return forward(self, images)

    monkeypatch.setattr(Classifier, "forward_raw", counted)
    return calls


def test_a_batch_is_one_victim_pass_and_each_frame_keeps_its_gradient(scene_dir, victim_dir, victim_calls):
    ctx = build_context(_config(scene_dir, victim_dir), scene_dir)
    T = start_texture(ctx)
    positions = list(range(N_FRAMES))
    alone = [frame_job(ctx, p, T, 0) for p in positions]
    assert victim_calls == [1] * N_FRAMES  # loss and prediction from one forward pass per frame
    victim_calls.clear()
    together = frame_jobs(ctx, positions, T, 0)
    assert victim_calls == [N_FRAMES]
    scale = max(float(np.abs(r.grad).max()) for r in alone)
    assert scale > 0
    for a, b in zip(alone, together):
        # The simulator's film sums samples with parallel atomics: the frames themselves differ in
        # the last float32 bits from render to render, so the comparison is to float rounding.
        assert np.abs(a.grad - b.grad).max() <= 1e-5 * scale
        assert b.loss == pytest.approx(a.loss, rel=1e-5)
        assert b.prediction == a.prediction and b.finite and a.finite
        assert set(b.timings) == {"sim_render", "victim", "grad_render", "total"}
    victim_calls.clear()
    frame_jobs(replace(ctx, config=_config(scene_dir, victim_dir, victim_batch=3)), positions, T, 0)
    assert victim_calls == [3, 1]  # victim_batch bounds a pass; the frames in order


def test_a_run_batched_by_one_ends_where_a_batched_run_does(scene_dir, victim_dir, victim_calls, tmp_path):
    from scheduler.local import run_local
    from undream.store import open_store

    batched = run_local(_config(scene_dir, victim_dir), tmp_path / "all", progress=False)
    # 3 attack iterations of one pass over 4 frames; the evaluation: one pass for the benign
    # frames and one for the adversarial ones (PGD's final pick reads no loss: no third render)
    assert victim_calls == [N_FRAMES] * 5
    victim_calls.clear()
    single = run_local(_config(scene_dir, victim_dir, victim_batch=1), tmp_path / "one", progress=False)
    assert victim_calls == [1] * (5 * N_FRAMES)
    final = [np.load(tmp_path / name / "texture_final.npy") for name in ("all", "one")]
    assert np.array_equal(final[0], final[1])  # docs/runs.md: bit for bit
    assert single["loss_per_iteration"] == pytest.approx(batched["loss_per_iteration"], rel=1e-5)
    assert single["adversarial"] == batched["adversarial"] and single["benign"] == batched["benign"]
    with open_store(None, tmp_path / "all" / "store") as store:  # every frame keeps its own record
        jobs = store.jobs(batched["run_id"], 2)
        assert [j.frame for j in jobs] == list(range(N_FRAMES))
        assert all(j.status == "succeeded" and j.finite and j.attempts == 1 for j in jobs)
        assert len({j.loss for j in jobs}) == N_FRAMES
        assert all(set(j.result["prediction"]) == {"label", "score", "correct"} for j in jobs)
        assert len({j.grad_ref for j in jobs}) == N_FRAMES
    saved = json.loads((tmp_path / "all" / "results.json").read_text())
    assert saved["wall_time_seconds"]["victim"] > 0


def test_apgd_still_reads_the_last_textures_loss(scene_dir, victim_dir, victim_calls, tmp_path):
    from scheduler.local import run_local
    from undream.store import open_store

    cfg = _config(scene_dir, victim_dir, attack={"name": "apgd", "eps": 32.0, "steps": 3})
    res = run_local(cfg, tmp_path / "apgd", progress=False)
    assert victim_calls[-3:] == [N_FRAMES] * 3  # benign, last texture's loss, adversarial
    with open_store(None, tmp_path / "apgd" / "store") as store:
        pre = store.jobs(res["run_id"], 3, "pre")
        assert all(isinstance(j.result["loss"], float) for j in pre)
