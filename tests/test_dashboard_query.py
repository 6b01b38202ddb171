"""The dashboard's query logic, charts and pictures, without HTTP: plain data read through the store."""
from __future__ import annotations

import dataclasses
import datetime as dt
import io
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dashboard_data import WORKERS, RunShape, add_run, build_farm  # noqa: E402

from undream import charts  # noqa: E402
from undream.dashboard import fleet, grid, images, query, sweeps  # noqa: E402
from undream.dashboard.errors import BadRequest, NotFound, Unavailable, from_store_error  # noqa: E402
from undream.errors import StoreError  # noqa: E402
from undream.store import RUN_STATUSES, open_store  # noqa: E402


@pytest.fixture(scope="module")
def farm_store(tmp_path_factory):
    store = open_store(None, tmp_path_factory.mktemp("dash") / "blobs")
    farm = build_farm(store)
    yield store, farm
    store.close()


def _png_size(data: bytes) -> tuple[int, int]:
    from PIL import Image

    return Image.open(io.BytesIO(data)).size


def test_runs_overview_has_every_state_newest_first(farm_store):
    store, farm = farm_store
    rows = query.runs_page(store)["runs"]
    assert {r["status"] for r in rows} == set(RUN_STATUSES)
    assert len(rows) == 6 + len(farm.sweep_runs)
    created = [r["created"] for r in rows]
    assert created == sorted(created, reverse=True)
    by_id = {r["id"]: r for r in rows}
    running = by_id[farm.runs["running"]]
    assert (running["iteration"], running["steps"], running["phase"]) == (3, 6, "attack")
    assert (running["frames_done"], running["frames_total"]) == (1, 4)
    assert len(running["loss"]) == 3 and running["loss"] == sorted(running["loss"])
    assert running["eta_s"] is not None and running["eta_s"] >= 0
    assert by_id[farm.runs["done"]]["eta_s"] is None
    assert by_id[farm.runs["failed"]]["error"].startswith("frame 1 of iteration 3")
    evaluating = by_id[farm.runs["evaluating"]]
    assert (evaluating["phase"], evaluating["frames_done"]) == ("adversarial", 0)
    queued = by_id[farm.runs["queued"]]
    assert (queued["iteration"], queued["loss"], queued["frames_done"]) == (0, [], 0)


def test_list_reads_match_the_per_run_reads(farm_store):
    """The runs list reads iterations and job counts of all its runs in one query each; the grid reads
    the jobs' lines (the columns it shows)."""
    store, farm = farm_store
    ids = [farm.runs["running"], farm.runs["queued"], "00000000-0000-4000-8000-000000000000"]
    iters = store.iterations_of(ids)
    assert iters[ids[0]] == store.iterations(ids[0]) and iters[ids[1]] == [] and iters[ids[2]] == []
    lines = store.job_lines(ids[0])
    assert [(j.k, j.frame, j.status, j.attempts, j.worker, j.error, j.timings, j.result) for j in lines] == \
        [(j.k, j.frame, j.status, j.attempts, j.worker, j.error, j.timings, j.result) for j in store.jobs(ids[0])]
    assert store.job_lines(ids[1]) == [] and lines[0].result["prediction"]["correct"] is True
    counts = store.job_counts(ids)
    assert counts[(ids[0], "attack", 3)] == {"succeeded": 1, "retried": 1, "started": 1, "queued": 1}
    assert counts[(ids[0], "attack", 0)] == {"succeeded": 4} and not any(key[0] != ids[0] for key in counts)


def test_runs_overview_filters_by_state_and_sweep(farm_store):
    store, farm = farm_store
    assert [r["id"] for r in query.runs_page(store, status="failed")["runs"]] == [farm.runs["failed"]]
    in_sweep = query.runs_page(store, sweep_id=farm.sweep_id)["runs"]
    assert sorted(r["id"] for r in in_sweep) == sorted(farm.sweep_runs)
    assert query.runs_page(store, status="running", sweep_id=farm.sweep_id)["runs"] == []
    with pytest.raises(BadRequest, match="'bogus': not a run status; valid statuses are queued"):
        query.runs_page(store, status="bogus")


def test_eta_follows_the_median_pace(farm_store):
    store, farm = farm_store
    run = store.get_run(farm.runs["running"])
    iters = store.iterations(run.id)
    last = iters[-1].created
    stamps = [run.created] + [r.created for r in iters]
    pace = sorted((b - a).total_seconds() for a, b in zip(stamps, stamps[1:]))[1]
    assert query._eta(run, iters, last) == pytest.approx(pace * 3)
    assert query._eta(run, iters, last + dt.timedelta(days=1)) == 0.0


def test_run_detail_has_iterations_frames_textures_and_config(farm_store):
    store, farm = farm_store
    detail = query.run_detail(store, farm.runs["done"])
    assert [r["k"] for r in detail["iterations"]] == list(range(6))
    assert all(r["seconds"] >= 0 for r in detail["iterations"])
    assert detail["textures"] == [0, 1, 2, 3, 4, 5, 6] and detail["final_texture"]
    assert detail["config"]["attack"] == {"name": "pgd", "eps": 32.0, "steps": 6}
    assert detail["evaluation"]["metric"] == "accuracy"
    assert detail["evaluation"]["benign"] == 1.0 and detail["evaluation"]["adversarial"] == 0.25
    frames = detail["frames"]
    assert [f["frame"] for f in frames] == [0, 1, 2, 3]
    assert frames[0]["benign"] == {"label": 4, "score": 0.9, "name": "trash_bin", "correct": True}
    assert frames[0]["adversarial"]["name"] == "umbrella" and frames[0]["adversarial"]["correct"] is False
    assert frames[3]["adversarial"]["correct"] is True
    with pytest.raises(StoreError, match="not found"):
        query.run_detail(store, "00000000-0000-4000-8000-000000000000")


def test_held_out_and_attacked_numbers_come_from_the_results(farm_store):
    store, farm = farm_store
    ev = query.run_detail(store, farm.runs["done"])["evaluation"]  # frame 3 held out; 3 of 4 fooled
    assert ev["held_out"] == {"frames": 1, "benign": 1.0, "adversarial": 1.0, "success_rate": 0.0}
    assert ev["attacked"] == {"frames": 3, "benign": 1.0, "adversarial": 0.0, "success_rate": 1.0}
    rows = {r["id"]: r for r in query.runs_page(store)["runs"]}
    done = rows[farm.runs["done"]]
    assert (done["held_out_benign"], done["held_out_adversarial"], done["adversarial"]) == (1.0, 1.0, 0.25)
    assert rows[farm.runs["running"]]["held_out_adversarial"] is None
    assert query.run_detail(store, farm.runs["running"])["evaluation"]["held_out"] is None


def test_accuracy_per_iteration_counts_the_attacked_frames_still_correct(farm_store):
    store, farm = farm_store
    points = query.chart_data(store, farm.runs["done"])["attacked"]
    assert [p["k"] for p in points] == list(range(6)) and {p["n"] for p in points} == {3}  # never frame 3
    assert [p["value"] for p in points] == pytest.approx([1, 1, 2 / 3, 2 / 3, 1 / 3, 1 / 3])
    assert all(j.frame != 3 for j in store.jobs(farm.runs["done"], None, "attack"))
    running = query.chart_data(store, farm.runs["running"])["attacked"]
    assert [p["n"] for p in running] == [4, 4, 4, 1]  # k = 3: one job done so far; failed ones not counted
    jobs = store.jobs(farm.runs["done"], None, "attack")
    old = [dataclasses.replace(j, result=None) for j in jobs[:3]]  # stored before jobs kept predictions
    detector = [dataclasses.replace(j, result={"prediction": {"detected": j.frame == 0, "score": 0.7}})
                for j in jobs[3:6]]
    assert query.attacked_metric(old + detector) == [{"k": 1, "value": pytest.approx(1 / 3), "n": 3}]


def test_sweep_rows_have_the_held_out_numbers(farm_store):
    store, farm = farm_store
    rows = sweeps.sweep_detail(store, farm.sweep_id)["rows"]
    by_eps = {(r["attack.name"], r["attack.eps"]): r for r in rows}
    assert by_eps[("mifgsm", 32)]["held_out_adversarial"] == 0.0  # every frame fooled, frame 3 too
    assert by_eps[("pgd", 8)]["held_out_adversarial"] == 1.0 and by_eps[("pgd", 8)]["held_out_benign"] == 1.0


def test_texture_versions_keep_the_first_and_latest():
    class Run:
        iteration = 99
    picked = query.texture_versions(Run(), most=8)  # type: ignore[arg-type]
    assert picked[0] == 0 and picked[-1] == 99 and len(picked) == 8
    Run.iteration = 3
    assert query.texture_versions(Run()) == [0, 1, 2, 3]  # type: ignore[arg-type]


def test_job_grid_marks_failed_retried_started_and_slow_jobs(farm_store):
    store, farm = farm_store
    g = grid.job_grid(store, farm.runs["running"])
    assert g["columns"] == ["0", "1", "2", "3"] and len(g["rows"]) == 4
    current = [row[3] for row in g["rows"]]
    assert [c["status"] for c in current] == ["succeeded", "retried", "started", "queued"]
    assert current[1]["error"].startswith("RenderError: Mitsuba ran out of memory") and current[1]["attempts"] == 1
    assert current[2]["worker"] == WORKERS[2]
    slow = {(f, k) for f, row in enumerate(g["rows"]) for k, c in enumerate(row) if c and c["slow"]}
    assert slow == {(3, 1), (0, 1)}  # the two jobs made 5× slower (k = 1, frame 3; k = 3 // 2, frame 0)
    assert g["slow_after_seconds"] == pytest.approx(2 * g["median_seconds"])
    assert g["counts"] == {"succeeded": 13, "retried": 1, "started": 1, "queued": 1}


def test_job_grid_ends_with_the_evaluation_columns(farm_store):
    store, farm = farm_store
    g = grid.job_grid(store, farm.runs["done"])
    assert g["columns"][-2:] == ["benign", "adversarial"] and g["n_iterations"] == 6
    assert all(row[-1]["status"] == "succeeded" and not row[-1]["slow"] for row in g["rows"])
    assert grid.job_grid(store, farm.runs["queued"])["rows"] == [[], [], [], []]


def test_sweep_detail_and_eps_series(farm_store):
    store, farm = farm_store
    detail = sweeps.sweep_detail(store, farm.sweep_id)
    assert detail["name"] == "eps-sweep" and sorted(detail["grid"]) == ["attack.eps", "attack.name"]
    assert [r["run"] for r in detail["rows"]] == farm.sweep_runs
    assert detail["statuses"] == {"done": 6}
    assert {(r["attack.name"], r["attack.eps"]) for r in detail["rows"]} == \
        {(a, e) for a in ("pgd", "mifgsm") for e in (8, 16, 32)}
    series = detail["series"]
    assert list(series) == ["mifgsm", "pgd"]
    assert [p["eps"] for p in series["pgd"]] == [8.0, 16.0, 32.0]
    adv = [p["adversarial"] for p in series["pgd"]]
    assert adv == sorted(adv, reverse=True) and adv[0] > adv[-1]
    assert [p["held_out_adversarial"] for p in series["mifgsm"]] == [1.0, 1.0, 0.0]  # frame 3 falls at ε 32
    assert sweeps.sweeps_overview(store) == {"sweeps": [{"id": farm.sweep_id, "name": "eps-sweep",
                                                         "created": detail["created"], "runs": 6,
                                                         "statuses": {"done": 6}}], "total": 1}


def test_workers_overview_from_the_store(farm_store):
    store, farm = farm_store
    now = dt.datetime.now(dt.timezone.utc)
    data = fleet.workers_overview(store, now=now)
    rows = {w["worker"]: w for w in data["workers"]}
    assert set(rows) == set(WORKERS)
    busy = rows[WORKERS[2]]
    assert busy["state"] == "busy" and busy["alive"]
    assert [(c["run_id"], c["phase"], c["k"], c["frame"]) for c in busy["current"]] == \
        [(farm.runs["running"], "attack", 3, 2)]
    assert sum(w["finished"] for w in rows.values()) > 0
    assert rows[WORKERS[0]]["jobs_per_minute"] == pytest.approx(rows[WORKERS[0]]["finished"] / 10)
    later = fleet.workers_overview(store, now=now + dt.timedelta(minutes=5), window_s=3600, alive_s=120)
    states = {w["worker"]: w["state"] for w in later["workers"]}
    assert states[WORKERS[2]] == "busy" and states[WORKERS[0]] == "silent"
    assert fleet.workers_overview(store, now=now + dt.timedelta(days=1))["workers"][0]["state"] == "busy"


def test_store_errors_map_to_404_or_503():
    assert isinstance(from_store_error(StoreError("run 'x': not found")), NotFound)
    try:
        try:
            raise OSError("disk gone")
        except OSError as exc:
            raise StoreError("get_run: database error at 'sqlite:///x': disk I/O error") from exc
    except StoreError as err:
        mapped = from_store_error(err)
    assert isinstance(mapped, Unavailable) and mapped.status == 503 and "\n" not in str(mapped)


def test_texture_png_enlarges_and_hatches_unseen_texels():
    from PIL import Image

    tex = np.full((8, 16, 3), 0.5, np.float32)
    seen = np.ones((8, 16), bool)
    seen[:, 12:] = False
    data = images.texture_png(tex, seen)
    img = np.asarray(Image.open(io.BytesIO(data)))
    assert img.shape == (128, 256, 3)  # 16× so that the short side reaches 128 px
    magenta = np.all(img == images.UNSEEN_RGB, axis=2)
    assert not magenta[:, : 12 * 16].any() and magenta[:, 12 * 16:].mean() == pytest.approx(2 / 6, abs=0.02)
    assert np.all(img[0, 0] == 128)


def test_seen_mask_from_state_or_gradients(farm_store):
    store, farm = farm_store
    seen = images.seen_mask(store, farm.runs["done"])
    assert seen.shape == (16, 32) and seen[:, :24].all() and not seen[:, 24:].any()
    rng = np.random.default_rng(1)
    no_state = add_run(store, RunShape("no-visible", "running", frames=2, steps=3, done_steps=1), rng)
    assert images.seen_mask(store, no_state) is not None  # from state; gradients are the fallback


def test_frame_png_is_the_frame_as_it_is():
    """The page enlarges a frame and lays a detector's boxes over it (undream.dashboard.overlay): the
    picture itself is never drawn on."""
    from PIL import Image

    frame = np.zeros((32, 32, 3), np.uint8)
    plain = np.asarray(Image.open(io.BytesIO(images.frame_png(frame))))
    assert plain.shape == (32, 32, 3) and plain.max() == 0
    with pytest.raises(StoreError, match="H×W×3 uint8"):
        images.frame_png(np.zeros((4, 4), np.float32))


def test_charts_are_pngs_with_their_size(farm_store):
    store, farm = farm_store
    detail = query.run_detail(store, farm.runs["done"])
    many = [{**detail["iterations"][0], "k": k} for k in range(charts.BARS_UP_TO + 1)]
    for data in (charts.loss_chart(detail["iterations"], "ce"), charts.seconds_chart(detail["iterations"]),
                 charts.seconds_chart(many), charts.seconds_chart([]),
                 charts.metric_chart(query.chart_data(store, farm.runs["done"])),
                 charts.metric_chart(query.chart_data(store, farm.runs["queued"])), charts.loss_chart([], None),
                 charts.metric_chart({"evaluation": {"metric": "ap50", "benign": 0.8, "adversarial": None},
                                      "steps": 3, "attacked": [{"k": 0, "value": 1.0, "n": 2}]}),
                 charts.sweep_chart(sweeps.eps_series(store, farm.sweep_id)), charts.sweep_chart({})):
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and _png_size(data) == (560, 270)


def test_sparkline_scales_into_the_box():
    pts = [tuple(map(float, p.split(","))) for p in charts.sparkline([1.0, None, 3.0, 2.0], 120, 24).split()]
    assert [p[0] for p in pts] == [1.0, pytest.approx(79.667, abs=0.05), 119.0]
    assert [p[1] for p in pts] == [23.0, 1.0, 12.0]
    assert charts.sparkline([1.0]) == "" and charts.sparkline([float("nan"), None]) == ""
