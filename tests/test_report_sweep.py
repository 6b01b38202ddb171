"""``undream report SWEEP``: the runs side by side. A sweep (attack.name × attack.eps × seed, 2 × 3 × 3
runs of 4 frames, built through the Store API: tests/dashboard_data.py, no rendering) whose seeds
differ and some of whose runs have not finished: one chart per metric, a table of mean ± sd per
cell over the finished seeds, comparison.csv, and the unfinished runs said to be unfinished."""
from __future__ import annotations

import csv
import io
import re
import statistics
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dashboard_data import RunShape, add_run  # noqa: E402

ATTACKS, EPS, SEEDS = ("pgd", "apgd"), (8, 16, 32), (0, 1, 2)
UNFINISHED = {("apgd", 32, 2): "running", ("apgd", 32, 1): "failed"}  # (attack, ε, seed) → status


def _held_out_value(attack: str, eps: int, seed: int) -> float:
    """The synthetic held-out adversarial accuracy: falls with ε, a little lower for apgd, varies by seed."""
    return round(max(0.0, 0.9 - eps / 40 - (0.1 if attack == "apgd" else 0.0) + 0.05 * (seed - 1)), 4)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> dict:
    from undream.store import open_store

    root = tmp_path_factory.mktemp("sweep")
    store = open_store(None, root / "blobs")
    spec = {"name": "budget", "run": "runs/bin_park_pgd.yaml",
            "grid": {"attack.name": list(ATTACKS), "attack.eps": list(EPS), "seed": list(SEEDS)}}
    sweep_id = store.create_sweep("budget", spec)
    rng = np.random.default_rng(0)
    try:
        for i, (attack, eps, seed) in enumerate((a, e, s) for a in ATTACKS for e in EPS for s in SEEDS):
            status = UNFINISHED.get((attack, eps, seed), "done")
            shape = RunShape(f"budget-{i:03d}", status, 4, 2, 2 if status == "done" else 1, attack=attack,
                             eps=float(eps), sweep_id=sweep_id, holdout="auto", extra={"seed": seed})
            run_id = add_run(store, shape, rng)
            if status == "done":
                results = store.get_run(run_id).results
                results["held_out"]["adversarial"]["value"] = _held_out_value(attack, eps, seed)
                store.set_results(run_id, results)
    finally:
        store.close()
    out = root / "rep"
    from undream.cli import main

    res = CliRunner().invoke(main, ["report", "budget", "--out", str(out), "--blobs", str(root / "blobs")],
                             env={"UNDREAM_DATABASE_URL": ""})
    assert res.exit_code == 0, res.output
    return {"out": out, "html": (out / "index.html").read_text()}


def test_one_chart_per_metric_with_the_progress_in_its_title(sweep):
    out, html = sweep["out"], sweep["html"]
    for metric in ("attacked", "held_out", "success"):
        assert f'src="compare_{metric}.png"' in html and (out / f"compare_{metric}.png").is_file()
    assert not (out / "compare_held_out_conditions.png").exists()  # no run holds a condition out
    assert "16 of 18 runs finished (1 failed, 1 running)" in html
    from PIL import Image

    with Image.open(out / "compare_held_out.png") as img:
        assert img.width == 560 and img.height > 270  # the chart and the command under it


def test_the_table_has_mean_and_sd_over_the_finished_seeds_per_cell(sweep):
    html = sweep["html"]
    table = html[html.index("<table id=comparison"):]
    table = table[:table.index("</table>")]
    rows = re.findall(r"<tr><td>(\w+)</td><td class=n>(\d+)</td>(.*?)</tr>", table)
    assert [(a, int(e)) for a, e, _ in rows] == [(a, e) for a in ATTACKS for e in EPS]
    for attack, eps, cells in rows:
        seeds = [s for s in SEEDS if (attack, int(eps), s) not in UNFINISHED]
        values = [100 * _held_out_value(attack, int(eps), s) for s in seeds]
        held = re.findall(r"<td class=n>(.*?)</td>", cells)[1]  # attacked, held out, success
        sd = f" ± {statistics.stdev(values):.1f}" if len(values) > 1 else ""
        count = "3" if len(seeds) == 3 else f"{len(seeds)} of 3"
        assert held == f"{statistics.fmean(values):.1f}{sd} % <span class=meta>({count})</span>", (attack, eps)


def test_comparison_csv_has_every_seed(sweep):
    rows = list(csv.DictReader(io.StringIO((sweep["out"] / "comparison.csv").read_text())))
    held = {(r["series"], r["x"]): r for r in rows if r["metric"] == "held_out"}
    assert len(held) == 6 and {r["x_axis"] for r in rows} == {"attack.eps"}
    cell = held[("pgd", "16")]
    assert [float(v) for v in cell["values"].split()] == [_held_out_value("pgd", 16, s) for s in SEEDS]
    assert float(cell["min"]) == _held_out_value("pgd", 16, 0) and float(cell["max"]) == _held_out_value("pgd", 16, 2)
    assert (held[("apgd", "32")]["n_seeds"], held[("apgd", "32")]["n_runs"]) == ("1", "3")


def test_unfinished_runs_are_listed_with_their_status_and_no_page(sweep):
    html, out = sweep["html"], sweep["out"]
    assert "budget-017" in html and "running: no page (a page needs a finished run)" in html
    assert "<td>running (step 1/2)</td>" in html  # the results table: how far an unfinished run got
    assert "failed: no page" in html
    assert len(list((out / "runs").iterdir())) == 16


def test_a_sweep_of_seeds_only_is_one_cell(tmp_path):
    from undream.report.compare import compare
    from undream.store import open_store

    store = open_store(None, tmp_path / "blobs")
    spec = {"name": "seeds", "run": "r.yaml", "grid": {"seed": [0, 1]}}
    sweep_id = store.create_sweep("seeds", spec)
    rng = np.random.default_rng(0)
    for s in (0, 1):
        add_run(store, RunShape(f"seeds-{s}", "done", 4, 2, 2, sweep_id=sweep_id, holdout="auto",
                                extra={"seed": s}), rng)
    side = compare(store.find_sweep(sweep_id), store.runs(sweep_id=sweep_id))
    store.close()
    assert side.x_axis is None and side.seed_axes == ("seed",)
    assert [(c.series, c.x, len(c.values)) for c in side.cells["held_out"]] == [("pgd", "all", 2)]


def test_a_sweep_with_no_finished_run_says_so(tmp_path):
    from undream.cli import main
    from undream.store import open_store

    store = open_store(None, tmp_path / "blobs")
    sweep_id = store.create_sweep("early", {"name": "early", "run": "r.yaml", "grid": {"attack.eps": [8, 16]}})
    for i, eps in enumerate((8, 16)):
        add_run(store, RunShape(f"early-{i}", "running", 4, 3, 1, eps=float(eps), sweep_id=sweep_id),
                np.random.default_rng(i))
    store.close()
    res = CliRunner().invoke(main, ["report", "early", "--out", str(tmp_path / "rep"), "--blobs",
                                    str(tmp_path / "blobs")], env={"UNDREAM_DATABASE_URL": ""})
    assert res.exit_code == 0, res.output
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "0 of 2 runs finished (2 running)" in html and "No run of this sweep has finished yet" in html
    assert "<img" not in html and html.count("<td>running (step 1/3)</td>") == 2


def test_a_grid_without_eps_puts_its_last_field_along_x_in_grid_order(tmp_path):
    from undream.report.charts import compare_png
    from undream.report.compare import compare, numeric_x
    from undream.store import open_store

    store = open_store(None, tmp_path / "blobs")
    spec = {"name": "losses", "run": "r.yaml", "grid": {"attack.name": ["pgd", "mifgsm"], "loss": ["margin", "ce"]}}
    sweep_id = store.create_sweep("losses", spec)
    for attack in ("pgd", "mifgsm"):
        for loss in ("margin", "ce"):
            add_run(store, RunShape(f"l-{attack}-{loss}", "done", 4, 2, 2, attack=attack, sweep_id=sweep_id,
                                    holdout="auto", extra={"loss": loss}), np.random.default_rng(0))
    side = compare(store.find_sweep(sweep_id), store.runs(sweep_id=sweep_id))
    store.close()
    assert (side.x_axis, side.series_axes, side.seed_axes) == ("loss", ("attack.name",), ())
    assert [(c.series, c.x) for c in side.cells["attacked"]] == [
        ("pgd", "margin"), ("pgd", "ce"), ("mifgsm", "margin"), ("mifgsm", "ce")]
    assert not numeric_x(side) and compare_png(side, "attacked", "undream report losses").startswith(b"\x89PNG")


def test_a_series_with_no_finished_run_is_left_out_of_its_chart():
    from undream.report.charts import compare_png
    from undream.report.compare import Cell, Comparison

    cells = [Cell("pgd", 16, "held_out", (0.5, 0.25), 3), Cell("apgd", 16, "held_out", (), 3)]
    side = Comparison("attack.eps", ("attack.name",), ("seed",), "ap50", {"held_out": cells}, {},
                      {"done": 2, "running": 4})
    assert compare_png(side, "held_out", "undream report s").startswith(b"\x89PNG")
