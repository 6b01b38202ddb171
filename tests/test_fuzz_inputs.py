"""Fuzzed specs and run configs: each one works or is one line naming its file, and leaves nothing behind.

700 generated inputs here (500 specs for ``undream init`` from five bases:
three trajectory YAMLs, a canonical sequence.json and an Unreal export; 200
run configs for ``undream run`` from two), derandomised so CI sees the same ones;
``scripts/fuzz_inputs.py --count 5000`` draws fresh ones and prints a table.
See tests/fuzz_support.py for how inputs are broken and judged.
"""
from __future__ import annotations

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings

from farm_support import make_scene, write_yaml
from fuzz_support import SPEC, SPEC_ACTORS, SPEC_KEYS, inputs, json_bases, outcome, run_doc

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


def _on(item, scene: str):
    """The placeholder scene of a generated run config pointed at the real one."""
    from fuzz_support import Input

    placeholder = b"SCENE" if b"SCENE" in item.data else b"SPEC"
    return Input(item.kind, item.how, item.data.replace(placeholder, scene.encode()))


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
