"""The v4 bundled classifier: the v3 data twice over (two parts under seeds 0 and 1), v3's training.

Its data distribution is v3's (tests/test_victims_v3.py); these check the shipped folder: the name,
its weights and card, the parts it was trained on, and that it loads offline and reads fresh renders.
"""
from __future__ import annotations

import pytest

from undream.errors import VictimError

from victims_support import check_offline, check_shipped, fresh_held_out


@pytest.fixture(scope="module")
def held_out_v3(tmp_path_factory):
    return fresh_held_out(tmp_path_factory, "v3")


def test_bundled_v4_name():
    from undream.victims import bundled_path, load_victim
    assert bundled_path("classifier-v4").name == "classifier-v4"
    with pytest.raises(VictimError, match="bundled victim 'classifier-v4': does classification, cannot do detection"):
        load_victim("bundled:classifier-v4", task="detection")
    with pytest.raises(VictimError, match="unknown; valid names are .*bundled:classifier-v4"):
        load_victim("bundled:detector-v4")  # no v4 detector is shipped


def test_bundled_v4_files():
    rec, card = check_shipped("classifier-v4", "v3", "accuracy", 0.95)
    assert rec["train_data"]["n"] == 16000 and rec["test"]["n_images"] == 1200
    assert [(p["n"], p["config"]["seed"], p["config"]["split"]) for p in rec["train_data"]["parts"]] == \
        [(8000, 0, "train"), (8000, 1, "train")]
    assert rec["test_data"]["config"]["seed"] == 0 and rec["config"]["epochs"] == 40
    assert card.startswith("# bundled:classifier-v4 — ResNet image classifier")
    assert "16000 images (seeds 0 and 1 (2 parts of 8000), split `train`)" in card
    assert "distribution `v3`" in card and "a plain one" in card
    assert "--data build/v4/train0 --data build/v4/train1" in card  # the command that made it


def test_bundled_v4_offline(monkeypatch, held_out_v3):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")
    check_offline("v4", held_out_v3, detector=False)  # no v4 detector
