"""scripts/physical_study.py: the smoothness, printability and detection rates of finished runs, grouped
over seeds (issue 44's table and Pareto chart, docs/results.md)."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "physical_study.py"


def _run_folder(root: Path, name: str, seed: int, texture: np.ndarray, detected: list[bool], tv: float = 0.0,
                attack: dict | None = None) -> Path:
    """A finished run's outputs as `undream run` writes them (the fields the script reads): 4 frames,
    frames 0-1 attacked, 2 held out, 3 a held-out condition."""
    folder = root / name
    folder.mkdir(parents=True)
    config = {"attack": attack or {"name": "pgd", "eps": 255.0}, "seed": seed, "gamut": "none",
              "regularise": {"tv": tv} if tv else None, "eot_print": None}
    (folder / "metadata.json").write_text(json.dumps({"config": config}))
    rows = lambda hits: [{"frame": i, "detected": h} for i, h in enumerate(hits)]  # noqa: E731
    part = lambda frames, b, a: {"frames": frames, "benign": {"value": b}, "adversarial": {"value": a}}  # noqa: E731
    results = {"benign": {"per_frame": rows([True] * 4)}, "adversarial": {"per_frame": rows(detected)},
               "attacked": part([0, 1], 1.0, 0.5), "held_out": part([2], 1.0, 0.0),
               "held_out_conditions": part([3], 1.0, 1.0)}
    (folder / "results.json").write_text(json.dumps(results))
    np.save(folder / "texture_final.npy", texture.astype(np.float32))
    return folder


def test_the_study_measures_each_texture_and_groups_the_seeds(tmp_path):
    flat = np.full((8, 8, 3), 0.5)
    stripes = np.zeros((8, 8, 3))
    stripes[:, 1::2] = 1.0  # every horizontal neighbour differs by 1, no vertical one: TV = 1
    runs = [_run_folder(tmp_path, "a0", 0, flat, [True, False, False, True]),
            _run_folder(tmp_path, "a1", 1, flat, [False, False, False, False]),
            _run_folder(tmp_path, "b0", 0, stripes, [True, True, True, True], tv=10),
            _run_folder(tmp_path, "w0", 0, np.ones((8, 8, 3)), [True, True, True, True], tv=1),
            _run_folder(tmp_path, "p0", 0, flat, [True] * 4, tv=10, attack={"name": "apgd", "eps": 255.0}),
            _run_folder(tmp_path, "q0", 0, flat, [False] * 4, tv=10,
                        attack={"name": "apgd", "eps": 255.0, "step_size": 21.0}),
            _run_folder(tmp_path, "r0", 0, flat, [False] * 4, tv=10,
                        attack={"name": "apgd", "eps": 255.0, "step_size": 21.0, "grad_blur": 4.0})]
    res = subprocess.run([sys.executable, str(SCRIPT), *map(str, runs), "--out", str(tmp_path / "study")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr
    with open(tmp_path / "study" / "runs.csv") as f:
        rows = {r["run"]: r for r in csv.DictReader(f)}
    assert float(rows["a0"]["tv"]) == 0.0 and abs(float(rows["b0"]["tv"]) - 1.0) < 1e-9
    assert float(rows["w0"]["nps"]) == 0.0  # paper white is a colour of the printable palette
    assert float(rows["b0"]["nps"]) > 0.0  # pure black is not (a press's black is dark grey)
    assert float(rows["a0"]["attacked_adversarial_rate"]) == 0.5
    assert float(rows["a0"]["held_out_conditions_adversarial_rate"]) == 1.0
    assert float(rows["a1"]["held_out_conditions_adversarial_rate"]) == 0.0
    with open(tmp_path / "study" / "groups.csv") as f:
        groups = {r["tv_weight"]: r for r in csv.DictReader(f) if r["attack"] == "pgd"}
    assert groups["0.0"]["seeds"] == "0 1"
    assert float(groups["0.0"]["held_out_conditions_adversarial_rate"]) == 0.5
    assert abs(float(groups["0.0"]["held_out_conditions_adversarial_rate_sd"]) - 2 ** -0.5) < 1e-9
    assert (tmp_path / "study" / "pareto.png").stat().st_size > 0
    assert "| PGD ε255, tv 10 | 0 |" in res.stdout
    # Auto-PGD's first step (attack.step_size) and a gradient blur make settings of their own
    assert "| Auto-PGD ε255, tv 10 | 0 |" in res.stdout and "| Auto-PGD ε255, η₀ 21, tv 10 | 0 |" in res.stdout
    assert "| Auto-PGD ε255, η₀ 21, gradient blur σ 4, tv 10 | 0 |" in res.stdout


def test_folders_without_results_are_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    res = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "empty"), "--out", str(tmp_path / "study")],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode != 0
    assert res.stderr.strip().splitlines() == ["no finished run among the folders given (none has results.json)"]
    assert not (tmp_path / "study").exists()
