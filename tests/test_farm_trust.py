"""What the farm promises and must keep (issue 19, "Trust"), each through the path a user takes.

- A frame whose victim gradient holds a NaN is dropped from the iteration's
  mean, even where the renderer's backward pass turned the NaN into a finite
  texture gradient.
- A worker that cannot write its blob folder or reach its database refuses to
  start with one line; a run whose start exhausts its retries ends ``failed``
  with the reason, shown by ``undream status``.
- Read-only commands never create a farm database.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from farm_support import make_scene, make_victim
from undream.spec.run import RunConfig


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    base = tmp_path_factory.mktemp("trust")
    return {"root": base, "victim": make_victim(base / "victim"), "scene": make_scene(base / "scene", 3, 16)}


# --- a NaN in the victim's image gradient -------------------------------------------------------

def _nan_victim_gradient(monkeypatch, positions: set[int]) -> None:
    """The victim's image gradient on frames ``positions`` is NaN over the left half of the image
    (its loss stays finite): the renderer's backward pass still gives a finite texture gradient
    from the right half, which must not be averaged in."""
    from undream.engine import job

    real = job.victim_loss_and_grad

    def nan_half(ctx, position, image_srgb):
        loss, g, record = real(ctx, position, image_srgb)
        if position in positions:
            g = g.copy()
            g[:, : g.shape[1] // 2] = np.nan
        return loss, g, record
    monkeypatch.setattr(job, "victim_loss_and_grad", nan_half)


def _config(tiny, steps: int = 1) -> RunConfig:
    return RunConfig(scene=str(tiny["scene"]), name="nan", victim=tiny["victim"], loss="ce", holdout="none",
                     attack={"name": "mifgsm", "eps": 32.0, "steps": steps}, gradient="prb", sim_spp=2, grad_spp=2,
                     eval_spp=1, seed=5)


def test_a_frame_with_a_nan_victim_gradient_is_dropped_from_the_step(tiny, tmp_path, monkeypatch):
    from scheduler.local import run_local
    from scheduler.state import decode_state
    from undream.engine.context import attack_of
    from undream.store import open_store

    _nan_victim_gradient(monkeypatch, {0})
    cfg = _config(tiny)
    res = run_local(cfg, tmp_path / "out", progress=False)
    store = open_store(None, tmp_path / "out" / "store")
    run_id = res["run_id"]
    rows = {g.frame: g for g in store.frame_grads(run_id, 0)}
    assert not rows[0].finite and rows[1].finite and rows[2].finite
    assert np.isfinite(rows[0].grad).all() and np.abs(rows[0].grad).sum() > 0  # what made it slip through
    (it,) = store.iterations(run_id)
    assert (it.n_ok, it.n_bad, it.dropped_frames) == (2, 1, [0])
    assert it.loss_mean == pytest.approx((rows[1].loss + rows[2].loss) / 2)
    # The step from the finite frames only, by the attack itself:
    attack = attack_of(cfg)
    T0 = torch.from_numpy(store.texture(run_id, 0))
    G = torch.from_numpy((rows[1].grad + rows[2].grad) / 2)
    expected, _ = attack.step(T0, G, it.loss_mean, decode_state(store.attack_state(run_id, 0) or {}))
    T1 = store.texture(run_id, 1)
    assert np.isfinite(T1).all()
    np.testing.assert_allclose(T1, expected.numpy(), atol=1e-6)
    assert res["frames_dropped_per_iteration"] == [1]


def test_every_frame_nan_still_fails_the_run(tiny, tmp_path, monkeypatch):
    from scheduler.iteration import AllFramesFailed
    from scheduler.local import run_local

    _nan_victim_gradient(monkeypatch, {0, 1, 2})
    with pytest.raises(AllFramesFailed, match="all 3 frames gave a non-finite gradient"):
        run_local(_config(tiny), tmp_path / "out", progress=False)
