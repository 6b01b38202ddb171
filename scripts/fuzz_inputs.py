#!/usr/bin/env python
"""Fuzz ``undream init --check`` and ``undream run --check`` with many generated inputs; print a table.

    .venv/bin/python scripts/fuzz_inputs.py --count 5000 [--seed 1] [--show 5]

Draws ``--count`` inputs (specs, run configs on a scene folder and on a spec file; see tests/fuzz_support.py
for how they are broken and judged), runs each through the command line
in-process, and prints how many of each kind were accepted, refused with one
line naming the file, or failed (a traceback, several lines, a message that
names no file, files left behind), with the first ``--show`` failures in
full. Exit status 1 when any input failed.
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
    parser.add_argument("--count", type=int, default=5000, help="inputs to try (default 5000)")
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
    from fuzz_support import SPEC, SPEC_ACTORS, SPEC_KEYS, Input, inputs, json_bases, outcome, run_doc

    seed = args.seed if args.seed is not None else random.randrange(2**31)
    with tempfile.TemporaryDirectory(prefix="undream-fuzz-") as tmp:
        root = Path(tmp)
        scene = str(make_scene(root / "scene", n_frames=2, size=16))
        spec = str(write_yaml(root / "spec.yaml", SPEC))
        work = root / "work"
        work.mkdir()
        kinds = [("spec", inputs("spec", SPEC)), ("spec with actors", inputs("spec", SPEC_ACTORS)),
                 ("spec with keyframes", inputs("spec", SPEC_KEYS)),
                 *((name, inputs("spec", base, ".json")) for name, base in json_bases().items()), ("run on a scene folder", inputs("run", run_doc(scene))),
                 ("run on a spec file", inputs("run", run_doc(spec)))]
        runner, table, failures = CliRunner(), Counter(), []
        start = time.monotonic()

        @hypothesis.seed(seed)
        @settings(max_examples=args.count, database=None, deadline=None, suppress_health_check=list(HealthCheck))
        @given(st.data())
        def explore(data: st.DataObject) -> None:
            label, strategy = kinds[data.draw(st.integers(0, len(kinds) - 1))]
            item: Input = data.draw(strategy)
            result = outcome(item, work, runner)
            verdict = "FAIL" if result.startswith("FAIL") else result
            table[(label, item.how, verdict)] += 1
            if verdict == "FAIL":
                failures.append((label, item, result))

        explore()
        seconds = time.monotonic() - start
    print(f"{sum(table.values())} inputs, seed {seed}, {seconds:.0f} s; failures: {len(failures)}\n")
    print("| input | broken by | result | count |\n|---|---|---|---|")
    for (label, how, verdict), n in sorted(table.items()):
        print(f"| {label} | {how} | {verdict} | {n} |")
    for label, item, result in failures[: args.show]:
        print(f"\n--- {label} ({item.how}): {item.data[:400]!r}\n{result}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
