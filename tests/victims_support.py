"""Helpers of the bundled-victim tests (v2, v3): parameter draws, tiny data sets made through the
command, and the checks every shipped version's weights and model card must pass."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from undream.spec.model import BACKGROUNDS, WEATHERS
from undream.training.dataset import CLASSES, DatasetConfig, _object_sphere, load_dataset, make_dataset


def draws(module: Any, split: str, n: int) -> list[Any]:
    """``n`` parameter draws of a distribution module's ``sample_params`` (nothing rendered)."""
    rng = np.random.default_rng([5, len(split)])
    spheres = [_object_sphere(c) for c in CLASSES]
    return [module.sample_params(rng, split, i % len(CLASSES), CLASSES[i % len(CLASSES)], spheres[i % len(CLASSES)])
            for i in range(n)]


def tiny_dataset(tmp_path_factory: Any, distribution: str, size: int) -> Path:
    """3 held-out images of ``size`` px at 2 spp, made through `undream victims make-dataset`."""
    from click.testing import CliRunner

    from undream.cli.victims import victims
    out = tmp_path_factory.mktemp(distribution) / "ds"
    res = CliRunner().invoke(victims, ["make-dataset", "--out", str(out), "--n", "3", "--seed", "1",
                                       "--split", "test", "--size", str(size), "--spp", "2",
                                       "--distribution", distribution, "--no-progress"])
    assert res.exit_code == 0, res.output
    return out


def fresh_held_out(tmp_path_factory: Any, distribution: str) -> Any:
    """12 fresh held-out images (a seed not used for the shipped test sets)."""
    out = tmp_path_factory.mktemp(f"held_out_{distribution}") / "ds"
    make_dataset(out, DatasetConfig(n=12, seed=20240, split="test", distribution=distribution), progress=False)
    return load_dataset(out)


def check_shipped(name: str, distribution: str, key: str, goal: float) -> tuple[dict, str]:
    """The shipped folder ``name``: its weights' size, the data it was made from, every held-out
    group present and at ``goal`` or above (overall too), the card showing the headline number;
    returns (its training record, its model card)."""
    from undream.training.model_card import MAX_WEIGHTS_BYTES, bundled_record, check_bundled
    info = check_bundled(name)
    assert 0 < info["weights_bytes"] <= MAX_WEIGHTS_BYTES
    rec = bundled_record(name)
    assert rec["train_data"]["config"]["distribution"] == rec["test_data"]["config"]["distribution"] == distribution
    assert rec["test"]["n_images"] >= 1000
    groups = rec["test"]["per_group"]
    assert set(groups["weather"]) == set(WEATHERS) and set(groups["background"]) == set(BACKGROUNDS)
    assert len(groups["height_m"]) == 5 and len(groups["distance_m"]) == 6  # every held-out band
    card = (Path(info["folder"]) / "MODEL_CARD.md").read_text()
    assert f"**{'accuracy' if key == 'accuracy' else 'AP@0.5'}: {rec['test'][key]:.3f}**" in card
    assert "| camera ground distance (m) | images |" in card
    assert rec["test"][key] >= goal
    assert min(g[key] for by in groups.values() for g in by.values()) >= goal  # and per group
    return rec, card


def check_offline(version: str, held_out: Any, detector: bool = True) -> None:
    """``bundled:classifier-<version>`` (a Hugging Face classifier of the bundled classes) and, with
    ``detector``, ``bundled:detector-<version>`` load without a network (HF_HUB_OFFLINE set by the
    caller) and are right on at least 10 of the 12 fresh images."""
    from undream.metrics import is_detected
    from undream.victims import load_victim
    from undream.victims.hf import HFClassifier
    x = torch.from_numpy(held_out.images).permute(0, 3, 1, 2).float() / 255.0
    classifier = load_victim(f"bundled:classifier-{version}")
    assert isinstance(classifier, HFClassifier) and classifier.labels == list(CLASSES)
    preds = classifier.predict(x)
    assert sum(p.label == y for p, y in zip(preds, held_out.labels.tolist())) >= 10
    if not detector:
        return
    dets = load_victim(f"bundled:detector-{version}").predict(x)
    hits = sum(is_detected(p, {"boxes": [b.tolist()], "labels": [int(y)]}, int(y))
               for p, b, y in zip(dets, held_out.boxes, held_out.labels))
    assert hits >= 10


def check_sample_unchanged(tmp_path: Path, fixture: Path) -> None:
    """Sample 0 of a data set made from ``fixture``'s config is the one recorded there: its drawn
    parameters exactly, its camera to 1e-9, its image's channel means to half a level."""
    import json
    ref = json.loads(fixture.read_text())
    make_dataset(tmp_path / "ds", DatasetConfig(**ref["config"]), progress=False)
    ds = load_dataset(tmp_path / "ds")
    rec = ds.records[0]
    assert rec["params"] == ref["record"]["params"]  # drawn by numpy alone: exact
    assert {k: rec[k] for k in ("label", "box", "visible_pixels", "redraws")} == \
        {k: ref["record"][k] for k in ("label", "box", "visible_pixels", "redraws")}
    np.testing.assert_allclose(rec["camera_to_world"], ref["record"]["camera_to_world"], atol=1e-9)
    np.testing.assert_allclose(ds.images[0].reshape(-1, 3).mean(0), ref["image_channel_means"], atol=0.5)
