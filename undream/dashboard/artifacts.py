"""Pictures by id, mounted at ``/artifacts``: textures, evaluation frames and charts as PNG.

Every URL names a run or sweep by its id (a UUID, checked by the route's
converter) and a picture by numbers and fixed names; the file behind it is
found through the store, never from the URL. Anything else is a 404. Picture
bytes are cached under a key that includes the run's ``updated`` time, so
a run that moves on gets new pictures.
"""
from __future__ import annotations

from typing import Any

from flask import Blueprint, Response

from undream import charts
from undream.dashboard import images, query, sweeps
from undream.dashboard.errors import NotFound
from undream.dashboard.state import farm

artifacts = Blueprint("artifacts", __name__)
CHARTS = ("loss", "metric", "seconds")
IMMUTABLE = "private, max-age=3600"  # a texture version before the latest never changes


def _seen(run_id: str) -> Any:
    """The run's seen-texel mask (fixed once iteration 0's jobs are in), cached."""
    store = farm().store()
    return farm().cache.get(("seen", run_id, store.has_texture(run_id, 1)),
                            lambda: images.seen_mask(store, run_id))


def _png(data: bytes, cache: str = "no-cache") -> Response:
    return Response(data, mimetype="image/png", headers={"Cache-Control": cache})


@artifacts.get("/runs/<id:run_id>/texture/<int:k>.png")
def texture(run_id: str, k: int) -> Any:
    """Texture version ``k`` (0 … the run's iteration), texels no frame sees hatched in magenta."""
    store = farm().store()
    run = store.get_run(run_id)
    if k > run.iteration or not store.has_texture(run_id, k):
        raise NotFound(f"run {run_id}: no texture for iteration {k} (the run is at iteration {run.iteration})")

    def make() -> bytes:
        return images.texture_png(store.texture(run_id, k), _seen(run_id))
    data = farm().cache.get(("texture", run_id, k, run.updated), make)
    return _png(data, IMMUTABLE if k < run.iteration else "no-cache")


@artifacts.get("/runs/<id:run_id>/texture/final.png")
def final_texture(run_id: str) -> Any:
    """The 8-bit texture the adversarial evaluation rendered."""
    store = farm().store()
    run = store.get_run(run_id)
    final = store.final_texture(run_id)
    if final is None:
        raise NotFound(f"run {run_id}: no final texture yet (status {run.status})")
    data = farm().cache.get(("final", run_id, run.updated),
                               lambda: images.texture_png(final, _seen(run_id)))
    return _png(data)


@artifacts.get("/runs/<id:run_id>/frames/<view>/<int:frame>.png")
def frame(run_id: str, view: str, frame: int) -> Any:
    """Evaluation frame ``frame`` of ``view`` (``benign`` or ``adversarial``) at its own size (the page
    enlarges it and lays a detector's boxes over it)."""
    if view not in query.EVAL_VIEWS:
        raise NotFound(f"frame view {view!r}: unknown; valid views are {', '.join(query.EVAL_VIEWS)}")
    store = farm().store()
    run = store.get_run(run_id)
    jobs = [j for j in store.jobs(run_id, run.iteration, query.EVAL_VIEWS[view])
            if j.frame == frame and j.status == "succeeded" and j.image_ref]
    if not jobs:
        raise NotFound(f"run {run_id}: no {view} frame {frame}")
    job = jobs[0]
    data = farm().cache.get(("frame", run_id, view, frame, job.finished),
                               lambda: images.frame_png(store.blobs.get_array(job.image_ref)))  # type: ignore[arg-type]
    return _png(data, IMMUTABLE)


@artifacts.get("/runs/<id:run_id>/charts/<name>.png")
def run_chart(run_id: str, name: str) -> Any:
    """Chart ``name`` of the run: ``loss``, ``metric`` (accuracy or AP@0.5) or ``seconds``."""
    if name not in CHARTS:
        raise NotFound(f"chart {name!r}: unknown; valid charts are {', '.join(CHARTS)}")
    store = farm().store()
    run = store.get_run(run_id)

    def make() -> bytes:
        detail = query.chart_data(store, run_id, farm().attack_jobs(run_id) if name == "metric" else [])
        if name == "loss":
            return charts.loss_chart(detail["iterations"], detail["loss_kind"])
        if name == "seconds":
            return charts.seconds_chart(detail["iterations"])
        return charts.metric_chart(detail)
    return _png(farm().cache.get(("chart", name, run_id, run.updated, run.iteration), make))


@artifacts.get("/sweeps/<id:sweep_id>/chart.png")
def sweep_chart(sweep_id: str) -> Any:
    """The sweep's adversarial accuracy / AP@0.5 against ε, one line per attack."""
    store = farm().store()
    series = sweeps.eps_series(store, store.find_sweep(sweep_id).id)
    return _png(charts.sweep_chart(series))
