"""Fuzzed specs, run configs, sweep files and command lines: each one works or is one line naming
its file, and a refused one leaves every byte on disk as it was.

1,280 generated cases here, derandomised so CI sees the same ones: 500 specs for
``undream init`` from five bases (three trajectory YAMLs, a canonical
sequence.json and an Unreal export), 200 run configs for ``undream run`` from
two and 60 multi-condition ones, 100 sweep files for ``undream sweep``, each meeting an absent ``--out``, a
user's folder or an earlier run's output, with or without ``--force`` (through
``--check``, then the real command when ``--check`` refuses); and 300 command
lines over every command (tests/fuzz_cli.py); 80 ``undream evaluate`` command lines with valid and
hostile textures, output files and holdouts, and 40 races for one output (tests/fuzz_outputs.py).
``scripts/fuzz_inputs.py --count
20000`` draws fresh ones and prints a table. See tests/fuzz_support.py and
tests/fuzz_cli.py for how inputs are broken and judged.
"""
from __future__ import annotations

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from farm_support import make_scene, write_yaml
from fuzz_cli import command_lines, judge, make_sandbox, sandbox_env
from fuzz_outputs import evaluate_cases, judge_evaluate, judge_race, make_evaluate_work, race_cases
from fuzz_support import (SPEC, SPEC_ACTORS, SPEC_KEYS, conditions_doc, inputs, json_bases, outcome, run_doc,
                          sweep_doc)

EXAMPLES = 100  # per base: 5 spec bases (2 of them JSON) + 2 run bases = 700 inputs
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz-bases")
    scene = make_scene(root / "scene", n_frames=2, size=16)
    spec_file = write_yaml(root / "spec.yaml", SPEC)
    work = tmp_path_factory.mktemp("fuzz-work")
    return {"scene": str(scene), "spec": str(spec_file), "work": work}


@pytest.fixture(scope="module")
def runner():
    return CliRunner()


def _judge(item, bases, runner):
    result = outcome(item, bases["work"], runner)
    assert not result.startswith("FAIL"), f"{item.kind} input ({item.how}) {item.data[:300]!r}: {result}"


@FUZZ
@given(item=inputs("spec", SPEC))
def test_fuzzed_specs(item, bases, runner):
    _judge(item, bases, runner)


@FUZZ
@given(item=inputs("spec", SPEC_ACTORS))
def test_fuzzed_specs_with_actors_and_per_frame_weather(item, bases, runner):
    _judge(item, bases, runner)


@FUZZ
@given(item=inputs("spec", SPEC_KEYS))
def test_fuzzed_specs_with_keyframes(item, bases, runner):
    _judge(item, bases, runner)


JSON = json_bases()


@FUZZ
@given(item=inputs("spec", JSON["sequence.json"], ".json"))
def test_fuzzed_canonical_sequences(item, bases, runner):
    _judge(item, bases, runner)


@FUZZ
@given(item=inputs("spec", JSON["Unreal export"], ".json"))
def test_fuzzed_unreal_exports(item, bases, runner):
    _judge(item, bases, runner)


@FUZZ
@given(data=inputs("run", run_doc("SCENE")))
def test_fuzzed_run_configs_on_a_scene_directory(data, bases, runner):
    _judge(_on(data, bases["scene"]), bases, runner)


@FUZZ
@given(data=inputs("run", run_doc("SPEC")))
def test_fuzzed_run_configs_on_a_spec_file(data, bases, runner):
    _judge(_on(data, bases["spec"]), bases, runner)


@settings(FUZZ, max_examples=60)
@given(data=inputs("run", conditions_doc("SPEC")))
def test_fuzzed_multi_condition_run_configs(data, bases, runner):
    _judge(_on(data, bases["spec"]), bases, runner)


@FUZZ
@given(data=inputs("sweep", sweep_doc("SCENE")))
def test_fuzzed_sweep_files(data, bases, runner):
    _judge(_on(data, bases["scene"]), bases, runner)


def _on(item, scene: str):
    """The placeholder scene of a generated run config or sweep pointed at the real one."""
    from dataclasses import replace

    placeholder = b"SCENE" if b"SCENE" in item.data else b"SPEC"
    return replace(item, data=item.data.replace(placeholder, scene.encode()))


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory, bases):
    from undream.cli import main

    box = make_sandbox(tmp_path_factory.mktemp("fuzz-cli"), SPEC, run_doc("SCENE"), bases["scene"])
    return box, CliRunner(env=sandbox_env(box)), main


@settings(FUZZ, max_examples=300)
@given(data=st.data())
def test_fuzzed_command_lines(data, sandbox):
    """Any command line: it works, or it is one line and exit 2 and changes nothing on disk; and
    no command, working or not, changes the user's own files."""
    box, runner, main = sandbox
    argv = data.draw(command_lines(box, main))
    result = judge(argv, box, runner)
    assert not result.startswith("FAIL"), f"{argv}: {result}"


def test_the_judge_catches_a_traceback_and_a_message_without_the_file(bases, runner, monkeypatch):
    """The fuzz test can fail: an exception the CLI does not map, and a line that names no file."""
    from fuzz_support import Input, dump

    import undream.scenedir.init as init

    def boom(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(init, "check_init", boom)
    assert outcome(Input("spec", "edited", dump(SPEC)), bases["work"], runner).startswith("FAIL: traceback")

    from undream.errors import SpecError

    def vague(*args, **kwargs):
        raise SpecError("something is wrong")

    monkeypatch.setattr(init, "check_init", vague)
    assert "does not name the file" in outcome(Input("spec", "edited", dump(SPEC)), bases["work"], runner)
    monkeypatch.undo()
    assert outcome(Input("spec", "edited", dump(SPEC)), bases["work"], runner) == "ok"


@pytest.fixture(scope="module")
def evaluate_work(tmp_path_factory, bases):
    from pathlib import Path

    return make_evaluate_work(tmp_path_factory.mktemp("fuzz-evaluate") / "work", Path(bases["scene"]))


@settings(FUZZ, max_examples=80)
@given(case=evaluate_cases())
def test_fuzzed_evaluate_textures_outputs_and_holdouts(case, evaluate_work, runner):
    """`undream evaluate` with valid and hostile textures, output files and holdouts: it works and
    writes whole outputs without touching an input, or it is one line and changes nothing."""
    result = judge_evaluate(case, evaluate_work, runner)
    assert not result.startswith("FAIL"), f"{case.how} --json {case.json_out!r} --csv {case.csv_out!r} " \
                                          f"--holdout {case.holdout!r}: {result}"


@settings(FUZZ, max_examples=40)
@given(case=race_cases())
def test_fuzzed_races_for_one_output(case, bases):
    """Threads claiming one new --out (run's and baseline's markers) or replacing one file at once:
    at most one claim wins, the losers are one line, a raced file holds one writer's bytes whole."""
    result = judge_race(case, bases["work"])
    assert not result.startswith("FAIL"), f"{case}: {result}"
