"""Adversarial training against attacked textures (issue 45): the shading a data set records, the
composite that puts any texture into its images, the PGD on the texture, and the command that
fine-tunes a classifier with it and writes its model card."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from undream.cli.victims import victims
from undream.training.adversarial import (AdversarialConfig, composite, composite_fidelity, load_shaded,
                                          pgd_textures)
from undream.errors import VictimError


def _make(out: Path, n: int, seed: int, split: str, shading: bool = True) -> Path:
    args = ["make-dataset", "--out", str(out), "--n", str(n), "--seed", str(seed), "--split", split,
            "--size", "32", "--spp", "4", "--distribution", "v3", "--no-progress"]
    res = CliRunner().invoke(victims, args + (["--shading"] if shading else []))
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def shaded(tmp_path_factory):
    root = tmp_path_factory.mktemp("shaded")
    return {"train": _make(root / "train", 6, 0, "train"), "test": _make(root / "test", 6, 0, "test"),
            "plain": _make(root / "plain", 2, 1, "test", shading=False)}


def test_make_dataset_shading_writes_each_images_shading(shaded):
    records = [json.loads(line) for line in (shaded["test"] / "labels.jsonl").read_text().splitlines()]
    assert len(records) == 6
    for rec in records:
        with np.load(shaded["test"] / rec["shading"]) as z:
            assert set(z.files) == {"black", "white", "uv", "coverage"}
            assert z["black"].shape == z["white"].shape == (32, 32, 3) and z["uv"].shape == (32, 32, 2)
            # the object reflects: brighter in white than in black where it shows
            on = z["coverage"] > 0.5
            assert on.any() and z["white"][on].astype(np.float32).mean() > 1.5 * z["black"][on].astype(np.float32).mean()
    meta = json.loads((shaded["test"] / "metadata.json").read_text())
    assert meta["config"]["shading"] is True


def test_the_same_images_with_or_without_shading(shaded, tmp_path):
    """--shading adds renders; it changes no image of the data set."""
    again = _make(tmp_path / "again", 2, 1, "test", shading=True)
    for name in ("00000.png", "00001.png"):
        assert (again / "images" / name).read_bytes() == (shaded["plain"] / "images" / name).read_bytes()


def test_the_composite_looks_a_texel_up_where_mitsuba_does():
    """Texel (row r, column c) of an S×S texture sits at uv ((c + ½)/S, (r + ½)/S), row 0 at v = 0,
    and the lookup wraps around (Mitsuba's bitmap, bilinear, repeat)."""
    s, r, c = 8, 2, 5
    tex = torch.zeros(1, s, s, 3)
    tex[0, r, c] = torch.tensor([1.0, 0.5, 0.25])
    uv = torch.tensor([[(c + 0.5) / s, (r + 0.5) / s], [(c + 0.5) / s + 1.0, (r + 0.5) / s - 1.0],
                       [(c + 1.0) / s, (r + 0.5) / s]]).view(1, 1, 3, 2)
    black, white = torch.zeros(1, 1, 3, 3), torch.ones(1, 1, 3, 3)
    img = composite(tex, black, white, uv)[0, :, 0, :].T  # 3 pixels × RGB, sRGB
    assert torch.allclose(img[0], tex[0, r, c], atol=1e-5)
    assert torch.allclose(img[1], tex[0, r, c], atol=1e-5)  # wrapped
    # halfway to the next (black) texel: half the linear value
    lin_half = ((img[2] + 0.055) / 1.055) ** 2.4
    lin_full = ((tex[0, r, c] + 0.055) / 1.055) ** 2.4
    assert torch.allclose(lin_half, lin_full / 2, atol=1e-4), (lin_half, lin_full)


def test_the_composite_of_each_images_own_texture_is_the_image(shaded):
    data = load_shaded(shaded["test"])
    fid = composite_fidelity(data)
    assert fid["psnr_db"] > 30.0, fid
    assert fid["object_mean_abs_255"] < 12.0, fid
    # the same shading with the texture's rows flipped (v → 1 − v) is further from the renders
    data.uv[..., 1] = 1.0 - data.uv[..., 1]
    assert composite_fidelity(data)["object_mean_abs_255"] > fid["object_mean_abs_255"]


def test_pgd_on_the_texture_stays_in_its_budget_and_raises_the_loss(shaded):
    from undream.victims.registry import load_victim

    data = load_shaded(shaded["test"])
    victim = load_victim("bundled:classifier-v3", task="classification")

    def logits_of(x):
        return victim.module(pixel_values=victim.preprocess(x)).logits

    idx = torch.arange(len(data))
    eps = torch.full((len(idx),), 16 / 255)
    adv = pgd_textures(logits_of, data, idx, eps, steps=5, gen=torch.Generator().manual_seed(0))
    assert (adv - data.textures).abs().max() <= 16 / 255 + 1e-6
    assert adv.min() >= 0 and adv.max() <= 1
    with torch.no_grad():
        own = torch.nn.functional.cross_entropy(logits_of(composite(data.textures, **data.batch(idx))), data.labels)
        att = torch.nn.functional.cross_entropy(logits_of(composite(adv, **data.batch(idx))), data.labels)
    assert att > own


def test_train_adversarial_through_the_command(shaded, tmp_path):
    out = tmp_path / "at"
    res = CliRunner().invoke(victims, [
        "train-adversarial", "--base", "bundled:classifier-v3", "--data", str(shaded["train"]),
        "--test", str(shaded["test"]), "--out", str(out), "--epochs", "1", "--steps", "2", "--eval-steps", "2",
        "--threads", "1"])
    assert res.exit_code == 0, res.output
    rec = json.loads((out / "training.json").read_text())
    adv = rec["adversarial"]
    assert set(adv["held_out"]["robust"]) == {"16", "50", "255"} == set(adv["held_out_base"]["robust"])
    assert adv["config"]["eps"] == [16, 50, 255] and adv["base"] == "bundled:classifier-v3"
    card = (out / "MODEL_CARD.md").read_text()
    assert "## Robust accuracy (held-out)" in card and "texture attacked, ε 255" in card
    assert "bundled:classifier-v3" in card
    from undream.victims.registry import load_victim
    assert load_victim(str(out), task="classification").num_classes == 6


@pytest.mark.parametrize("args, says", [
    (["--eps", "0"], "eps: budgets must be integers in 1..255"),
    (["--eps", "16,x"], "budgets must be integers in 1..255"),
    (["--base", "bundled:nope"], "bundled victim 'nope': unknown"),
])
def test_bad_settings_are_one_line(shaded, tmp_path, args, says):
    base = ["train-adversarial", "--base", "bundled:classifier-v3", "--data", str(shaded["train"]),
            "--test", str(shaded["test"]), "--out", str(tmp_path / "x")]
    res = CliRunner().invoke(victims, base + args)
    assert res.exit_code == 2 and says in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_data_without_shading_is_refused_by_name(shaded, tmp_path):
    res = CliRunner().invoke(victims, [
        "train-adversarial", "--base", "bundled:classifier-v3", "--data", str(shaded["plain"]),
        "--test", str(shaded["test"]), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "has no shading" in res.output and "--shading" in res.output, res.output
    assert not (tmp_path / "x").exists()


def test_config_checks():
    with pytest.raises(VictimError, match="clean_share"):
        AdversarialConfig(clean_share=1.0)
    with pytest.raises(VictimError, match="steps"):
        AdversarialConfig(steps=0)
