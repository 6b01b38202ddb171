"""The v2 bundled victims: their data distribution (camera height and ground distance, every
background and weather, banded held-out split), v1 data unchanged, the bundled names and
aliases, and the per-group evaluation report."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from undream.errors import DatasetError, VictimError
from undream.spec.model import BACKGROUNDS, WEATHERS
from undream.training import distribution_v2 as v2
from undream.training.bands import band_count, band_index
from undream.training.dataset import CLASSES, DatasetConfig, _object_sphere, load_dataset, splits_of
from undream.training.evaluation import evaluate
from undream.training.model_card import group_tables

from victims_support import check_offline, check_sample_unchanged, check_shipped, draws, fresh_held_out, tiny_dataset

FIXTURES = Path(__file__).resolve().parent / "fixtures"
SIZE = 32


def _draws(split: str, n: int) -> list[v2.SampleParamsV2]:
    return draws(v2, split, n)


@pytest.fixture(scope="module")
def drawn() -> dict[str, list[v2.SampleParamsV2]]:
    """Parameters only (nothing rendered): 600 draws per split."""
    return {s: _draws(s, 600) for s in ("train", "test")}


@pytest.fixture(scope="module")
def tiny_v2(tmp_path_factory) -> Path:
    """3 held-out v2 images of 32 px at 2 spp, made through the command."""
    return tiny_dataset(tmp_path_factory, "v2", SIZE)


# --------------------------------------------------------------------------- the v2 sampler

def test_v2_bands_are_disjoint_between_splits(drawn):
    seen: dict[str, dict[str, set[int]]] = {"train": {}, "test": {}}
    for split, ps in drawn.items():
        for p in ps:
            values = v2.banded_values({"azimuth_deg": p.azimuth_deg, "height_m": p.height_m,
                                       "distance_m": p.distance_m, "fov_deg": p.fov_deg,
                                       "environment": p.environment.to_json()})
            assert {k: (band_index(v2.BANDS_V2, k, v) % 2) for k, v in values.items()} == \
                {k: ("train", "test").index(split) for k in values}, values
            for name in ("height_m", "distance_m"):
                seen[split].setdefault(name, set()).add(band_index(v2.BANDS_V2, name, values[name]))
    for name in ("height_m", "distance_m"):
        assert not seen["train"][name] & seen["test"][name]
        assert seen["train"][name] | seen["test"][name] == set(range(band_count(v2.BANDS_V2, name)))


def test_v2_test_bands_lie_between_training_bands():
    for name in v2.BANDS_V2:
        assert band_count(v2.BANDS_V2, name) % 2 == 1 or name == "azimuth_deg", name
    assert v2.BANDS_V2["height_m"][:2] == (0.2, 3.5) and v2.BANDS_V2["distance_m"][:2] == (1.5, 8.0)


def test_v2_every_background_and_weather_in_both_splits(drawn):
    assert set(v2.WEATHER_WEIGHTS_V2) == set(WEATHERS)
    for ps in drawn.values():
        assert {p.environment.weather for p in ps} == set(WEATHERS)
        assert {p.environment.background for p in ps} == set(BACKGROUNDS)
        days = [p.environment.time_of_day for p in ps if p.environment.weather != "night"]
        assert min(days) < 8.5 and max(days) > 17.5  # across the day


def test_v2_frames_the_object(drawn):
    """Camera outside the bounding sphere, at its height and ground distance, the object spanning COVERAGE."""
    for p in drawn["test"][:60]:
        centre, radius = _object_sphere(p.name)
        seq = v2.sample_frame(p, (centre, radius), SIZE, seed=0)
        eye = np.asarray(seq.frames[0].camera.to_world.matrix)[:3, 3]
        assert eye[1] == pytest.approx(p.height_m)
        world_centre = np.asarray(seq.frames[0].object_to_world.matrix)[:3, :3] @ centre
        assert math.hypot(eye[0] - world_centre[0], eye[2] - world_centre[2]) == pytest.approx(p.distance_m)
        assert np.linalg.norm(eye - world_centre) > radius
        assert v2.COVERAGE[0] <= p.coverage <= v2.COVERAGE[1]


def test_bad_distribution():
    with pytest.raises(DatasetError, match=r"distribution: must be one of v1, v2, v3, got 'v4'"):
        DatasetConfig(n=1, seed=0, distribution="v4")


def test_tiny_v2_dataset(tiny_v2):
    ds = load_dataset(tiny_v2)
    assert ds.images.shape == (3, SIZE, SIZE, 3)
    meta = json.loads((tiny_v2 / "metadata.json").read_text())
    assert meta["distribution"] == "v2" and meta["config"]["distribution"] == "v2"
    assert meta["bands"]["height_m"] == [0.2, 3.5, 0.3]
    for rec in ds.records:
        assert splits_of(rec["params"]) == {"test"}
        assert rec["visible_pixels"] >= v2.min_visible_pixels(SIZE) == 15


def test_v1_sample_unchanged(tmp_path):
    """Sample 0 of a v1 data set is what the code before v2 rendered (tests/fixtures/v1_sample.json)."""
    check_sample_unchanged(tmp_path, FIXTURES / "v1_sample.json")


# --------------------------------------------------------------------------- names

def test_bundled_names_and_aliases():
    from undream.victims import bundled_names, bundled_path
    assert bundled_path("classifier-v1") == bundled_path("classifier")
    assert bundled_path("detector-v1") == bundled_path("detector")
    assert bundled_path("classifier-v2").name == "classifier-v2"
    assert bundled_path("detector-v2").name == "detector-v2"
    assert bundled_names() == ["classifier", "detector", "classifier-v2", "detector-v2", "classifier-v3",
                               "detector-v3", "classifier-v4", "classifier-at", "yolo",
                               "classifier-v1", "detector-v1"]


def test_unknown_bundled_name_lists_the_valid_ones():
    from undream.victims import load_victim
    with pytest.raises(VictimError, match=r"bundled victim 'classifier-v9': unknown; valid names are "
                       r"bundled:classifier, bundled:detector, bundled:classifier-v2, bundled:detector-v2, "
                       r"bundled:classifier-v3, bundled:detector-v3, bundled:classifier-v4, bundled:classifier-at, bundled:yolo, "
                       r"bundled:classifier-v1, "
                       r"bundled:detector-v1"):
        load_victim("bundled:classifier-v9")


def test_alias_keeps_the_task_check():
    from undream.victims import load_victim
    with pytest.raises(VictimError, match="bundled victim 'detector-v1': does detection, cannot do classification"):
        load_victim("bundled:detector-v1", task="classification")


# --------------------------------------------------------------------------- the per-group report

class _Stub:
    """A victim that answers the truth (or a wrong class for images in ``wrong``)."""

    def __init__(self, task: str, ds, wrong: set[int]) -> None:
        self.task, self.ds, self.wrong, self.name, self.seen = task, ds, wrong, "stub", 0

    def predict(self, x: torch.Tensor, threshold: float = 0.5):
        from undream.victims.base import ClassPrediction, DetPrediction
        out = []
        for i in range(self.seen, self.seen + len(x)):
            y = int(self.ds.labels[i]) if i not in self.wrong else (int(self.ds.labels[i]) + 1) % len(CLASSES)
            if self.task == "classification":
                out.append(ClassPrediction(label=y, probs=torch.eye(len(CLASSES))[y]))
            else:
                out.append(DetPrediction(torch.tensor(self.ds.boxes[i:i + 1]), torch.tensor([0.9]),
                                         torch.tensor([y])))
        self.seen += len(x)
        return out


@pytest.mark.parametrize("task, measure", [("classification", "accuracy"), ("detection", "ap50")])
def test_per_group_report(tiny_v2, task, measure):
    ds = load_dataset(tiny_v2)
    result = evaluate(_Stub(task, ds, wrong={0}), ds)
    groups = result["per_group"]
    assert list(groups) == ["weather", "background", "height_m", "distance_m"]
    for grouping, by in groups.items():
        assert sum(g["n"] for g in by.values()) == 3, grouping
    rec = ds.records[0]
    weather = groups["weather"][rec["params"]["environment"]["weather"]]
    assert weather[measure] < 1.0  # image 0 is wrong, and counts in its own weather
    for name in ("height_m", "distance_m"):
        for band in groups[name]:
            lo = float(band.strip("[)").split(",")[0])
            assert band_index(v2.BANDS_V2, name, lo + 1e-6) % 2 == 1  # a test band
    lines = group_tables(result)
    assert "| camera height (m) | images | " + ("accuracy" if task == "classification" else "AP@0.5") + " |" in lines


# --------------------------------------------------------------------------- the shipped v2 weights

GOALS = {"classifier-v2": ("accuracy", 0.95), "detector-v2": ("ap50", 0.90)}  # issue 22's, overall and per group


@pytest.fixture(scope="module")
def held_out_v2(tmp_path_factory):
    return fresh_held_out(tmp_path_factory, "v2")


@pytest.mark.parametrize("name", list(GOALS))
def test_bundled_v2_files(name):
    check_shipped(name, "v2", *GOALS[name])


def test_bundled_v2_offline(monkeypatch, held_out_v2):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    check_offline("v2", held_out_v2)
