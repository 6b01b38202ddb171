"""The adversarially trained bundled classifier (issue 45): bundled:classifier-v3 fine-tuned against
textures attacked in the loop. These check the shipped folder: its name and task, the record of how it
was made (base, budgets, data with shading), the card's clean and robust accuracy on the held-out split
(benign ≥ 0.9), and that it loads offline and reads fresh renders."""
from __future__ import annotations

import pytest

from undream.errors import VictimError

from victims_support import check_offline, fresh_held_out


@pytest.fixture(scope="module")
def held_out_v3(tmp_path_factory):
    return fresh_held_out(tmp_path_factory, "v3")


def test_bundled_at_name_and_task():
    from undream.victims import bundled_path, load_victim
    assert bundled_path("classifier-at").name == "classifier-at"
    with pytest.raises(VictimError, match="bundled victim 'classifier-at': does classification, cannot do detection"):
        load_victim("bundled:classifier-at", task="detection")


def test_bundled_at_record_and_card():
    from pathlib import Path

    from undream.training.model_card import MAX_WEIGHTS_BYTES, bundled_record, check_bundled, model_card
    info = check_bundled("classifier-at")
    assert 0 < info["weights_bytes"] <= MAX_WEIGHTS_BYTES
    rec = bundled_record("classifier-at")
    adv = rec["adversarial"]
    assert adv["base"] == "bundled:classifier-v3"
    assert rec["train_data"]["config"]["shading"] is True and rec["test_data"]["config"]["shading"] is True
    assert rec["train_data"]["config"]["distribution"] == rec["test_data"]["config"]["distribution"] == "v3"
    assert rec["test_data"]["config"]["split"] == "test" and rec["test"]["n_images"] == adv["held_out"]["n_images"]
    # the goal: benign accuracy >= 0.9 on the held-out split, rendered and composited
    assert rec["test"]["accuracy"] >= 0.9 and adv["held_out"]["clean"] >= 0.9 and adv["held_out"]["composite"] >= 0.9
    assert set(adv["held_out"]["robust"]) >= {"16", "50", "255"}
    assert adv["composite_fidelity"]["test"]["psnr_db"] > 30
    card = (Path(info["folder"]) / "MODEL_CARD.md").read_text()
    assert card == model_card(info["folder"])  # the card says what the record says
    assert card.startswith("# bundled:classifier-at — adversarially trained ResNet image classifier")
    for eps in ("16", "50", "255"):
        row = (f"| texture attacked, ε {eps} | {adv['held_out_base']['robust'][eps]:.3f} | "
               f"{adv['held_out']['robust'][eps]:.3f} |")
        assert row in card


def test_bundled_at_offline(monkeypatch, held_out_v3):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")
    check_offline("at", held_out_v3, detector=False)
