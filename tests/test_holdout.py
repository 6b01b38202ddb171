"""Held-out frames: the attack never renders them for a gradient, and the evaluation reports them apart."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
import datetime as dt

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from farm_support import make_scene, make_victim, run_config, write_yaml
from scheduler.iteration import attacked_frames, expected_frames
from undream.errors import SpecError
from undream.spec.run import RunConfig, split_frames
from undream.store import RunSnapshot

ROOT = Path(__file__).resolve().parents[1]


def test_split_frames_known_answers():
    assert split_frames("auto", 8) == ([0, 1, 2, 4, 5, 6], [3, 7])
    assert split_frames("auto", 24)[1] == [3, 7, 11, 15, 19, 23]
    assert split_frames("auto", 3) == ([0, 1, 2], [])  # too short to hold any out
    assert split_frames("none", 5) == ([0, 1, 2, 3, 4], [])
    assert split_frames({"every": 3, "offset": 1}, 7) == ([0, 2, 3, 5, 6], [1, 4])
    assert split_frames({"frames": [4, 0, 4]}, 5) == ([1, 2, 3], [0, 4])


@pytest.mark.parametrize("holdout, n, needle", [
    ({"frames": [9]}, 4, "holdout.frames: must be positions below the sequence's 4 frames"),
    ({"every": 1}, 4, "holdout.every"),
    ({"frames": [0, 1]}, 2, "holds out all 2 frames"),
    ("most", 4, 'holdout: must be "auto"'),
    ({"every": 2, "frames": [1]}, 4, "holdout: must be"),
])
def test_bad_holdouts_name_the_field(holdout, n, needle):
    with pytest.raises(SpecError, match=needle.replace("(", r"\(").replace(")", r"\)")):
        split_frames(holdout, n)


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 40), every=st.integers(2, 9), offset=st.integers(0, 9),
       per_step=st.one_of(st.none(), st.integers(1, 40)), k=st.integers(0, 500), seed=st.integers(0, 2**31 - 1))
def test_no_iteration_ever_draws_a_held_out_frame(n, every, offset, per_step, k, seed):
    holdout = {"every": every, "offset": offset}
    held_all = not [f for f in range(n) if f < offset or (f - offset) % every]
    if held_all:  # refused with a SpecError (test_bad_holdouts_name_the_field)
        return
    attacked, held = split_frames(holdout, n)
    if per_step is not None and per_step > len(attacked):
        return
    run = _stored({"holdout": holdout}, n, seed)
    frames = expected_frames(run, per_step, k)
    assert frames and not set(frames) & set(held)
    assert set(frames) <= set(attacked) and sorted(set(attacked) | set(held)) == list(range(n))
    assert frames == expected_frames(run, per_step, k)  # a retried iteration draws the same frames


def _stored(config: dict, n_frames: int, seed: int) -> RunSnapshot:
    """A run as the store hands it out, its config as stored (``scene`` and ``config`` only)."""
    now = dt.datetime.now(dt.timezone.utc)
    return RunSnapshot(id="r", name="r", config={"scene": "x", **config}, status="running", iteration=0,
                       n_frames=n_frames, seed=seed, created=now, updated=now, error=None,
                       attack_state_ref=None, results=None)


def test_a_run_stored_before_holdout_attacks_every_frame():
    run = _stored({}, 8, 0)
    assert attacked_frames(run) == list(range(8))
    assert RunConfig(scene="x").holdout == "auto"  # new runs hold out by default


def test_a_run_never_attacks_its_held_out_frames_and_reports_them_apart(tmp_path):
    scene = make_scene(tmp_path / "scene", n_frames=8, size=16)
    victim = make_victim(tmp_path / "victim")
    cfg = run_config(scene, victim, name="held", steps=5, attack={"frames_per_step": 3})
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(tmp_path / "run.yaml", cfg)),
                          "--out", str(out), "--no-progress"], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert "held-out frames (2)" in res.stdout

    from undream.store import open_store

    with open_store(None, out / "store") as store:
        (run,) = store.runs()
        attack_jobs = store.jobs(run.id, None, "attack")
        evaluated = {j.frame for j in store.jobs(run.id, run.iteration, "adversarial")}
    attacked = {j.frame for j in attack_jobs}
    assert len(attack_jobs) == 5 * 3 and attacked and not attacked & {3, 7}
    assert evaluated == set(range(8))  # held-out frames are judged, never attacked
    results = json.loads((out / "results.json").read_text())
    assert results["held_out"]["frames"] == [3, 7]
    assert results["attacked"]["frames"] == [0, 1, 2, 4, 5, 6]
    assert not set(results["attacked"]["frames"]) & set(results["held_out"]["frames"])
    per_frame = {row["frame"]: row for row in results["adversarial"]["per_frame"]}
    held_accuracy = sum(per_frame[f]["correct"] for f in (3, 7)) / 2
    assert results["held_out"]["adversarial"]["value"] == held_accuracy
