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


def test_an_oracles_csv_reads_its_oracle_column(tmp_path):
    """scripts/condition_oracle.py writes `oracle` where condition_budget.py writes `adversarial`."""
    oracle = tmp_path / "oracle.csv"
    with open(oracle, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["victim", "condition", "attack", "eps", "steps", "seed", "frames",
                                               "benign", "oracle", "run_wall_s"])
        writer.writeheader()
        for condition, score in (("night", 0.5), ("street", 0.25)):
            writer.writerow({"victim": "v", "condition": condition, "attack": "apgd", "eps": 16, "steps": 200,
                             "seed": 0, "frames": 24, "benign": 1, "oracle": score, "run_wall_s": 1})
    a = _csv(tmp_path / "a.csv", {"night": [1.0, 0.75], "street": [1.0, 1.0]}, attack="apgd")
    res = _heatmap("--out", str(tmp_path / "h.png"), "--study", f"attacked elsewhere={a}",
                   "--study", f"oracle={oracle}")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[4] == "| oracle | 0.50 | 0.25 | 0.38 |"
    assert lines[3] == "| attacked elsewhere | 1.00 / 0.75 | 1.00 / 1.00 | 0.94 ± 0.09 |"


def test_a_csv_of_several_runs_needs_run(tmp_path):
    """condition_budget.py writes one scene and 16 conditions into one CSV: read as one study, each
    condition's cell held both runs' seeds."""
    both = tmp_path / "both.csv"
    one = _csv(tmp_path / "one.csv", {"night": [0.5]})
    many = _csv(tmp_path / "many.csv", {"night": [0.0]})
    lines = one.read_text().splitlines() + many.read_text().replace("64 conditions", "16 conditions").splitlines()[1:]
    both.write_text("\n".join(lines) + "\n")
    res = _heatmap("--out", str(tmp_path / "h.png"), "--study", f"x={both}")
    assert res.returncode == 2 and "give --run" in res.stderr, res.stderr
    res = _heatmap("--out", str(tmp_path / "h.png"), "--study", f"x={both}", "--run", "16 conditions")
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[3] == "| x | 0.00 | 0.00 |"
