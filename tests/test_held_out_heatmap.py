"""scripts/held_out_heatmap.py: the held-out conditions × studies chart and table of the docs."""
from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["victim", "run", "attack", "eps", "seed", "condition", "frames", "benign", "adversarial", "run_wall_s"]


def _csv(path: Path, scores: dict[str, list[float]], attack: str = "pgd") -> Path:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        for condition, per_seed in scores.items():
            for seed, score in enumerate(per_seed):
                writer.writerow({"victim": "v", "run": "64 conditions", "attack": attack, "eps": 255, "seed": seed,
                                 "condition": condition, "frames": 24, "benign": 0.875 if condition == "street" else 1,
                                 "adversarial": score, "run_wall_s": 1})
    return path


def _heatmap(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "held_out_heatmap.py"), *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_rows_read_every_seed_and_the_mean_over_conditions(tmp_path):
    a = _csv(tmp_path / "a.csv", {"night": [0.25, 0.0, 0.0], "street": [0.0, 0.0, 0.125]})
    b = _csv(tmp_path / "b.csv", {"night": [0.0, 0.0, 0.0], "street": [0.0, 0.5, 0.0]})
    res = _heatmap("--out", str(tmp_path / "h.png"), "--study", f"one=a={a}", "--study", f"two={b}")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == "| study | night | street | mean of the conditions |"
    assert lines[2] == "| benign texture | 1.00 | 0.88 | 0.94 |"
    assert lines[3] == "| one=a | 0.25 / 0.00 / 0.00 | 0.00 / 0.00 / 0.12 | 0.06 ± 0.06 |"  # a label may hold '='
    assert lines[4] == "| two | 0.00 / 0.00 / 0.00 | 0.00 / 0.50 / 0.00 | 0.08 ± 0.14 |"
    assert (tmp_path / "h.png").stat().st_size > 10_000


def test_a_missing_csv_or_attack_is_one_line_and_writes_nothing(tmp_path):
    a = _csv(tmp_path / "a.csv", {"night": [0.0]})
    for study, needle in ((f"one={tmp_path / 'missing.csv'}", "existing CSV"), (str(a), "LABEL=CSV")):
        res = _heatmap("--out", str(tmp_path / "h.png"), "--study", study)
        assert res.returncode == 2 and needle in res.stderr.strip().splitlines()[-1], res.stderr
    res = _heatmap("--out", str(tmp_path / "h.png"), "--study", f"one={a}", "--attack", "apgd")
    assert res.returncode == 2 and "no rows of attack 'apgd'" in res.stderr
    assert not (tmp_path / "h.png").exists()
