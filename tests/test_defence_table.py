"""scripts/defence_table.py: the defence table of issue 45 from finished runs (a row per victim, defence
and attack; a column per budget, mean ± sd over the seeds; the adaptive rows' distance from the
undefended victim)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "defence_table.py"


def _run(root: Path, name: str, victim: str, defence: dict | None, eps: int, seed: int, adv: float,
         benign: float = 1.0, steps: int = 20) -> Path:
    """A finished run's outputs as `undream run` writes them (the fields the script reads)."""
    folder = root / name
    folder.mkdir(parents=True)
    config = {"victim": victim, "defence": defence, "attack": {"name": "pgd", "eps": float(eps), "steps": steps},
              "seed": seed,
              "eval_spp": 16}
    (folder / "metadata.json").write_text(json.dumps({"config": config}))
    part = {"benign": {"value": benign}, "adversarial": {"value": adv}}
    (folder / "results.json").write_text(json.dumps({"held_out_conditions": part, "held_out": part, "attacked": part}))
    return folder


def test_the_table_groups_seeds_and_measures_each_defence_against_the_undefended_victim(tmp_path):
    jpeg = {"steps": [{"jpeg": 75}], "backward": "auto", "adaptive": True, "draws": 1}
    pad = {"steps": [{"resize_pad": {"scale": [0.8, 1.0], "pad": 0.15, "fill": 0.5}}], "backward": "auto",
           "adaptive": True, "draws": 2}
    runs = [_run(tmp_path, "u0", "bundled:classifier-v3", None, 16, 0, 0.2),
            _run(tmp_path, "u1", "bundled:classifier-v3", None, 16, 1, 0.4),
            _run(tmp_path, "j0", "bundled:classifier-v3", jpeg, 16, 0, 0.25, benign=0.9),
            _run(tmp_path, "j1", "bundled:classifier-v3", jpeg, 16, 1, 0.35, benign=0.9),
            _run(tmp_path, "p0", "bundled:classifier-v3", pad, 16, 0, 0.8),
            _run(tmp_path, "a0", "bundled:classifier-at", None, 16, 0, 0.5),
            _run(tmp_path, "u100", "bundled:classifier-v3", None, 16, 0, 0.1, steps=100),
            _run(tmp_path, "a100", "bundled:classifier-at", None, 16, 0, 0.15, steps=100)]
    out = tmp_path / "table"
    done = subprocess.run([sys.executable, str(SCRIPT), *map(str, runs), "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    lines = (out / "table.md").read_text().splitlines()
    assert lines[0] == "| victim | defence | attack | steps | benign | ε 16 | adaptive − undefended |"
    rows = {tuple(c.strip() for c in line.strip("|").split("|")[:4]): line for line in lines[2:]}
    # mean ± sample sd over the two seeds
    assert "| 1.00 ± 0.00 | 0.30 ± 0.14 |" in rows[("bundled:classifier-v3", "none", "undefended", "20")]
    # within 0.10 of the undefended 0.30: bypassed; 0.80 is 0.50 above it: the defence holds
    assert rows[("bundled:classifier-v3", "jpeg 75", "adaptive", "20")].endswith("| 0.90 ± 0.00 | 0.30 ± 0.07 | +0.00: bypassed |")
    assert rows[("bundled:classifier-v3", "resize_pad fill 0.5, pad 0.15, scale [0.8, 1.0] (EOT 2 draws)",
                 "adaptive", "20")].endswith("| 0.80 | +0.50: holds |")
    # another victim without a defence is the attack on that victim itself
    assert rows[("bundled:classifier-at", "none", "adaptive", "20")].endswith("| 0.50 | +0.20: holds |")
    # a longer attack is measured against the undefended victim under as many steps
    assert rows[("bundled:classifier-at", "none", "adaptive", "100")].endswith("| 0.15 | +0.05: bypassed |")
    assert [line.split("|")[1].strip() for line in lines[2:]][0] == "bundled:classifier-v3"
