"""scripts/condition_oracle.py: each condition attacked on its own frames and judged there (an oracle that
bounds what a texture attacked elsewhere can do; docs/runs.md, "An oracle at ε = 16")."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

from farm_support import make_victim, write_yaml
from test_conditions import SPEC

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "condition_oracle.py"


def _oracle(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, cwd=ROOT)


def test_every_condition_and_seed_is_attacked_on_its_own_frames_and_read_back_when_done(tmp_path, mi):
    conditions = tmp_path / "conditions"
    conditions.mkdir()
    write_yaml(conditions / "clear.yaml", SPEC)
    write_yaml(conditions / "fog.yaml", {**SPEC, "environment": {**SPEC["environment"], "weather": "fog"}})
    victim = make_victim(tmp_path / "victim")
    args = ["--out", tmp_path / "out", "--victim", victim, "--eps", 32, "--attack", "pgd", "--steps", 2,
            "--seeds", 1, "--conditions-dir", conditions]
    first = _oracle(*args)
    assert first.returncode == 0, first.stderr
    slug = str(victim).replace(":", "_").replace("/", "_")  # the victim as the script names its files
    table = tmp_path / "out" / f"oracle_{slug}_pgd_eps32_steps2.csv"
    with open(table) as f:
        rows = list(csv.DictReader(f))
    assert [(r["condition"], r["seed"]) for r in rows] == [("clear", "1"), ("fog", "1")]
    for r in rows:  # each row is its run's own judgement of every frame it attacked (none held out)
        run = tmp_path / "out" / "runs" / slug / f"oracle_{r['condition']}_pgd_eps32_steps2_seed{r['seed']}"
        results = json.loads((run / "results.json").read_text())
        assert results["held_out"] is None and results["attacked"]["frames"] == [0, 1, 2, 3]
        assert float(r["oracle"]) == results["attacked"]["adversarial"]["value"]
        assert float(r["benign"]) == results["attacked"]["benign"]["value"]
        assert results["attack"]["seed"] == int(r["seed"])
    assert "| mean of the 2 |" in first.stdout
    stamps = sorted((p, p.stat().st_mtime_ns) for p in (tmp_path / "out" / "runs").rglob("results.json"))
    again = _oracle(*args)  # a second start reads the finished runs
    assert again.returncode == 0, again.stderr
    assert sorted((p, p.stat().st_mtime_ns) for p in (tmp_path / "out" / "runs").rglob("results.json")) == stamps
    with open(table) as f:
        assert list(csv.DictReader(f)) == rows


def test_an_unknown_condition_is_refused_before_anything_runs(tmp_path):
    res = _oracle("--out", tmp_path / "out", "--victim", "bundled:classifier-v3", "--eps", 16,
                  "--conditions", "fog", "moon")
    assert res.returncode == 2 and "--conditions: moon is not one of camera_far" in res.stderr
    assert not (tmp_path / "out").exists()
