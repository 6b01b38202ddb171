"""One typed run config (issue 20): the attack block parsed once, complete, stored normalised at submit,
and read everywhere through :class:`undream.spec.run.RunConfig` (``RunSnapshot.run_config``).

Before: a run whose YAML omitted ``attack.steps`` ran the attack's default of 100 steps while
``undream status`` and the dashboard found no step count ("0/None", the wrong phase, no ETA); the
report read ``grad_spp`` with a fallback of 8 where the default is 16; 19 places read the raw dict.
"""
from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path

import pytest

from farm_support import Farm, farm_inputs, run_config, write_yaml
from undream.spec.attack import AttackConfig
from undream.spec.run import RunConfig

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_STEPS = AttackConfig.__dataclass_fields__["steps"].default


def test_the_attack_block_is_complete_and_follows_the_runs_seed():
    config = RunConfig.from_json({"scene": "s", "seed": 7, "attack": {"name": "pgd", "eps": 16}})
    assert isinstance(config.attack, AttackConfig)
    assert config.attack.steps == DEFAULT_STEPS and config.attack.seed == 7 and config.attack.eps == 16.0
    stored = config.to_json()
    assert stored["attack"] == dataclasses.asdict(config.attack)  # every field, defaults filled in
    assert RunConfig.from_json(json.loads(json.dumps(stored))) == config  # the stored form reads back equal
    assert RunConfig.from_json({"scene": "s", "seed": 7, "attack": {"name": "pgd", "seed": 3}}).attack.seed == 3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    return farm_inputs(tmp_path_factory, "typed", 2)


@pytest.mark.slow  # a real broker and CLI subprocesses
def test_a_run_without_attack_steps_shows_its_real_step_count_in_status_and_the_dashboard(tiny, tmp_path):
    """Through the commands: submit a run whose YAML gives no ``attack.steps`` (no worker runs it), then
    ``undream status``, the stored row and the dashboard's JSON all say the steps it will run."""
    from undream.dashboard import create_app

    cfg = run_config(tiny["scene"], tiny["victim"], name="nosteps")
    del cfg["attack"]["steps"]
    run_yaml = write_yaml(tmp_path / "run.yaml", cfg)
    farm = Farm(tmp_path / "farm")
    try:
        run_id = farm.submit(run_yaml)
        status = farm.cli("status")
        assert status.returncode == 0, status.stderr
        row = next(line for line in status.stdout.splitlines() if run_id[:8] in line)
        assert f"0/{DEFAULT_STEPS}" in row and "None" not in row, row
        stored = farm.store.get_run(run_id).config["attack"]
        assert stored["steps"] == DEFAULT_STEPS and stored["seed"] == cfg["seed"]  # normalised at submit
        client = create_app(farm.settings()).test_client()
        answer = client.get(f"/api/runs/{run_id}").get_json()
        assert answer["steps"] == DEFAULT_STEPS, answer
    finally:
        farm.stop()


def test_the_report_reads_grad_spp_through_the_type(tmp_path):
    """A stored config without ``grad_spp`` (an older run) reads the run config's default (16), not the
    report's own fallback of 8."""
    from undream.store import open_store

    with open_store(None, tmp_path / "blobs") as store:
        run_id = store.create_run("old", {"scene": "s", "attack": {"name": "pgd", "eps": 8}}, 4, 0)
        run = store.get_run(run_id)
    assert run.run_config.grad_spp == RunConfig.__dataclass_fields__["grad_spp"].default == 16
    assert run.run_config.attack.steps == DEFAULT_STEPS


# Modules that may read a stored run's raw config: none but the type's own (RunSnapshot.run_config).
RAW_READS_ALLOWED: set[str] = set()


def test_no_module_reads_a_runs_raw_config():
    """``run.config.get(...)`` / ``run.config[...]`` anywhere in the library is a second, untyped reading of
    the run config; each one names its file and line here."""
    found = []
    for folder in ("undream", "scheduler", "workers"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            if rel in RAW_READS_ALLOWED:
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                target = None
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get":
                    target = node.func.value
                elif isinstance(node, ast.Subscript):
                    target = node.value
                owner = getattr(target, "value", None)
                if isinstance(target, ast.Attribute) and target.attr == "config" and (
                        (isinstance(owner, ast.Name) and owner.id == "run")
                        or (isinstance(owner, ast.Attribute) and owner.attr == "run")):
                    found.append(f"{rel}:{node.lineno}")
    assert not found, "raw run-config reads (use run.run_config): " + ", ".join(found)
