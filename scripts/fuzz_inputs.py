#!/usr/bin/env python
"""Fuzz every command with many generated inputs and command lines; print a table of outcomes.

    .venv/bin/python scripts/fuzz_inputs.py --count 20000 [--seed 1] [--show 5]

Draws ``--count`` cases, each one of: a broken spec for ``undream init``, a
broken run config for ``undream run`` (on a scene folder, on a spec file, and
a multi-condition one), a broken sweep file for ``undream sweep``, each
meeting an absent ``--out``, a user's folder or an earlier run's output
(``--check`` first, then the real command when ``--check`` refuses); a
generated command line of any command; an ``undream evaluate`` with a valid or
hostile texture, output files that may or may not be replaced, and a holdout;
or threads racing for one new output folder or one output file
(tests/fuzz_support.py, tests/fuzz_cli.py and tests/fuzz_outputs.py say how
cases are made and judged). Prints how many of each kind were accepted, refused with
one line, or failed (a traceback, several lines, a message that names
neither the input nor ``--out``, a byte changed on disk by a refused
command, a user's file changed by any command), with the first ``--show``
failures in full. Exit status 1 when any case failed.
"""
from __future__ import annotations

import argparse
import os
import random
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=20000, help="cases to try (default 20000)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the draws (default: random)")
    parser.add_argument("--show", type=int, default=5, help="failures to print in full")
    args = parser.parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sys.path.insert(0, str(ROOT / "tests"))
    import hypothesis
    from click.testing import CliRunner
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from farm_support import make_scene, write_yaml
    from fuzz_cli import command_lines, judge, make_sandbox, sandbox_env
    from fuzz_outputs import evaluate_cases, judge_evaluate, judge_race, make_evaluate_work, race_cases
    from fuzz_support import (SPEC, SPEC_ACTORS, SPEC_KEYS, conditions_doc, inputs, json_bases, outcome, run_doc,
                              sweep_doc)
    from undream.cli import main as undream

    seed = args.seed if args.seed is not None else random.randrange(2**31)
    with tempfile.TemporaryDirectory(prefix="undream-fuzz-") as tmp:
        root = Path(tmp)
        scene = make_scene(root / "scene", n_frames=2, size=16)
        spec = str(write_yaml(root / "spec.yaml", SPEC))
        work = root / "work"
        work.mkdir()
        box = make_sandbox(root / "box", SPEC, run_doc(str(scene)), scene)
        kinds = [("spec", inputs("spec", SPEC)), ("spec with actors", inputs("spec", SPEC_ACTORS)),
                 ("spec with keyframes", inputs("spec", SPEC_KEYS)),
                 *((name, inputs("spec", base, ".json")) for name, base in json_bases().items()),
                 ("run on a scene folder", inputs("run", run_doc(str(scene)))),
                 ("run on a spec file", inputs("run", run_doc(spec))),
                 ("run with conditions", inputs("run", conditions_doc(spec))),
                 ("sweep", inputs("sweep", sweep_doc(str(scene)))), ("command line", command_lines(box, undream)),
                 ("evaluate", evaluate_cases()), ("race", race_cases())]
        evaluate_work = make_evaluate_work(root / "evaluate", scene)
        runner, cli_runner = CliRunner(), CliRunner(env=sandbox_env(box))
        table, failures = Counter(), []
        start = time.monotonic()

        @hypothesis.seed(seed)
        @settings(max_examples=args.count, database=None, deadline=None, suppress_health_check=list(HealthCheck))
        @given(st.data())
        def explore(data: st.DataObject) -> None:
            label, strategy = kinds[data.draw(st.integers(0, len(kinds) - 1))]
            case = data.draw(strategy)
            if label == "command line":
                result, how = judge(case, box, cli_runner), case[0]
            elif label == "evaluate":
                result, how = judge_evaluate(case, evaluate_work, runner), case.how
            elif label == "race":
                result, how = judge_race(case, work), f"{case.what} from {case.start}"
            else:
                result, how = outcome(case, work, runner), case.how
            verdict = "FAIL" if result.startswith("FAIL") else result
            table[(label, how, verdict)] += 1
            if verdict == "FAIL":
                failures.append((label, case, result))

        explore()
        seconds = time.monotonic() - start
    print(f"{sum(table.values())} cases, seed {seed}, {seconds:.0f} s; failures: {len(failures)}\n")
    print("| case | broken by / command | result | count |\n|---|---|---|---|")
    for (label, how, verdict), n in sorted(table.items()):
        print(f"| {label} | {how} | {verdict} | {n} |")
    for label, case, result in failures[: args.show]:
        shown = case if label in ("command line", "evaluate", "race") else \
            f"({case.how}, --out {case.out}): {case.data[:400]!r}"
        print(f"\n--- {label} {shown}\n{result}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
