"""The v3 bundled victims: their data distribution (v2's camera, environments and bands, with
plain, unsaturated textures too), v2 data unchanged, the bundled names, and the shipped weights."""
from __future__ import annotations

import colorsys
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from undream.errors import VictimError
from undream.spec.model import BACKGROUNDS, WEATHERS
from undream.training import distribution_v2 as v2
from undream.training import distribution_v3 as v3
from undream.training.bands import band_index
from undream.training.dataset import CLASSES, _object_sphere, load_dataset, splits_of
from undream.training.textures import (PLAIN_SATURATION, PLAIN_SHARE, PLAIN_VALUE, TEXTURE_KINDS_V3, make_texture,
                                       plain_recipe)

from victims_support import check_offline, check_sample_unchanged, check_shipped, draws, fresh_held_out, tiny_dataset

FIXTURES = Path(__file__).resolve().parent / "fixtures"
SIZE = 32
N_DRAWS = 600


@pytest.fixture(scope="module")
def drawn() -> dict[str, list[v2.SampleParamsV2]]:
    """Parameters only (nothing rendered): 600 v3 draws per split."""
    return {s: draws(v3, s, N_DRAWS) for s in ("train", "test")}


@pytest.fixture(scope="module")
def tiny_v3(tmp_path_factory) -> Path:
    """3 held-out v3 images of 32 px at 2 spp, made through the command."""
    return tiny_dataset(tmp_path_factory, "v3", SIZE)


# --------------------------------------------------------------------------- the v3 sampler

def test_v3_plain_textures_stay_in_their_ranges(drawn):
    plain = [p.texture for ps in drawn.values() for p in ps if p.texture["kind"] == "plain"]
    share = len(plain) / (2 * N_DRAWS)
    assert abs(share - PLAIN_SHARE) < 0.05, share  # binomial sd about 0.013
    for t in plain:
        (colour,) = t["colours"]
        _, s, v = colorsys.rgb_to_hsv(*colour)
        assert PLAIN_SATURATION[0] <= s <= PLAIN_SATURATION[1] + 1e-9, t
        assert PLAIN_VALUE[0] - 1e-9 <= v <= PLAIN_VALUE[1] + 1e-9, t
    greys = [t for t in plain if colorsys.rgb_to_hsv(*t["colours"][0])[1] < 0.05]
    assert greys and min(colorsys.rgb_to_hsv(*t["colours"][0])[2] for t in plain) < 0.2  # greys, dark ones too
    kinds = {p.texture["kind"] for ps in drawn.values() for p in ps}
    assert kinds == set(TEXTURE_KINDS_V3)


@pytest.mark.parametrize("split", ["train", "test"])
def test_v3_draws_the_camera_and_environment_of_v2(split):
    """Only the texture differs from a v2 draw from the same generator (it is drawn last)."""
    for i in range(60):
        label = i % len(CLASSES)
        args = (split, label, CLASSES[label], _object_sphere(CLASSES[label]))
        p2 = v2.sample_params(np.random.default_rng([9, i]), *args)
        p3 = v3.sample_params(np.random.default_rng([9, i]), *args)
        assert dataclasses.replace(p3, texture=p2.texture) == p2


def test_v3_bands_are_those_of_v2(drawn):
    assert v3.BANDS_V3 == v2.BANDS_V2 and v3.COVERAGE == v2.COVERAGE
    for split, ps in drawn.items():
        for p in ps:
            values = v3.banded_values({"azimuth_deg": p.azimuth_deg, "height_m": p.height_m,
                                       "distance_m": p.distance_m, "fov_deg": p.fov_deg,
                                       "environment": p.environment.to_json()})
            assert {band_index(v3.BANDS_V3, k, v) % 2 for k, v in values.items()} == {("train", "test").index(split)}
            assert v3.COVERAGE[0] <= p.coverage <= v3.COVERAGE[1]
        assert {p.environment.weather for p in ps} == set(WEATHERS)
        assert {p.environment.background for p in ps} == set(BACKGROUNDS)


@pytest.mark.parametrize("seed", range(6))
def test_plain_texture_is_one_colour(seed):
    recipe = plain_recipe(np.random.default_rng(seed))
    tex = make_texture(recipe, SIZE)
    assert tex.shape == (SIZE, SIZE, 3) and tex.dtype == np.float32
    np.testing.assert_allclose(tex.reshape(-1, 3), np.tile(np.float32(recipe["colours"][0]), (SIZE * SIZE, 1)))


def test_tiny_v3_dataset(tiny_v3):
    ds = load_dataset(tiny_v3)
    assert ds.images.shape == (3, SIZE, SIZE, 3)
    meta = json.loads((tiny_v3 / "metadata.json").read_text())
    assert meta["distribution"] == "v3" and meta["config"]["distribution"] == "v3"
    assert meta["bands"]["height_m"] == [0.2, 3.5, 0.3]
    assert meta["plain_textures"] == {"share": PLAIN_SHARE, "hsv_saturation": list(PLAIN_SATURATION),
                                      "hsv_value_srgb": list(PLAIN_VALUE)}
    for rec in ds.records:
        assert splits_of(rec["params"]) == {"test"}
        assert rec["visible_pixels"] >= v2.min_visible_pixels(SIZE)


def test_v2_sample_unchanged(tmp_path):
    """Sample 0 of a v2 data set is what the code before v3 rendered (tests/fixtures/v2_sample.json)."""
    check_sample_unchanged(tmp_path, FIXTURES / "v2_sample.json")


def test_v2_draws_keep_their_textures():
    """v2's sampler still draws v2 textures: no plain ones."""
    assert all(p.texture["kind"] != "plain" for p in draws(v2, "train", 300))


# --------------------------------------------------------------------------- the shipped v3 weights

GOALS = {"classifier-v3": ("accuracy", 0.95), "detector-v3": ("ap50", 0.90)}  # v2's: overall and per group


@pytest.fixture(scope="module")
def held_out_v3(tmp_path_factory):
    return fresh_held_out(tmp_path_factory, "v3")


def test_bundled_v3_names():
    from undream.victims import bundled_path, load_victim
    assert bundled_path("classifier-v3").name == "classifier-v3"
    assert bundled_path("detector-v3").name == "detector-v3"
    with pytest.raises(VictimError, match="bundled victim 'classifier-v3': does classification, cannot do detection"):
        load_victim("bundled:classifier-v3", task="detection")
    with pytest.raises(VictimError, match="bundled victim 'detector-v3': does detection, cannot do classification"):
        load_victim("bundled:detector-v3", task="classification")


@pytest.mark.parametrize("name", list(GOALS))
def test_bundled_v3_files(name):
    rec, card = check_shipped(name, "v3", *GOALS[name])
    assert rec["train_data"]["n"] == 8000 and rec["test"]["n_images"] == 1200
    assert "distribution `v3`" in card and "a plain one" in card
    assert "build/v3/train --n 8000" in card  # the commands that made it


def test_bundled_v3_offline(monkeypatch, held_out_v3):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")
    check_offline("v3", held_out_v3)
