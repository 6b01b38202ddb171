"""Every run config and sweep under examples/ is one a user can run: it loads and checks as written
(a typo in a field, a loss the victim's task lacks or a grid over a missing field fails here, not in a
user's first command)."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

from scheduler.sweep import load_sweep
from undream.scenedir.conditions import conditions_sequence
from undream.settings import load_local
from undream.spec.run import TASK_LOSSES, load_run_config
from undream.victims.registry import BUNDLED, bundled_folder_name, bundled_path

ROOT = Path(__file__).resolve().parents[1]
RUNS = sorted((ROOT / "examples" / "runs").glob("*.yaml"))
SWEEPS = sorted((ROOT / "examples" / "sweeps").glob("*.yaml"))


@pytest.mark.parametrize("path", RUNS, ids=[p.name for p in RUNS])
def test_every_example_run_config_loads(path):
    config = load_run_config(path)
    if config.victim.startswith("bundled:"):  # the bundled victim exists and does the loss's task
        folder = bundled_folder_name(config.victim.removeprefix("bundled:"))  # an unknown name raises
        assert bundled_path(folder).is_dir()
        assert config.loss in TASK_LOSSES[BUNDLED[folder]]
    if config.conditions is not None:  # every condition composes: its files are found from the config's folder
        grids = [grid for _, grid in config.conditions.placed_grids()]
        expected = (sum(math.prod(map(len, g.values())) for g in grids) if grids else 1) + len(config.conditions.scenes)
        assert len(conditions_sequence(config, path.parent, load_local().undream_cache).conditions) == expected


@pytest.mark.parametrize("path", SWEEPS, ids=[p.name for p in SWEEPS])
def test_every_example_sweep_expands(path):
    sweep = load_sweep(path)
    assert sweep.runs
