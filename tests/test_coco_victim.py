"""coco:centernet, a real COCO detector read from its TF.js graph: parity with the
official TF.js runtime on real photographs, what it finds in them, its gradients,
and bad inputs (an op the loader does not know, weights of another shape, a
class COCO does not have, a model setup has not fetched), one line each."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from coco_support import (CACHE_HOME, PARITY_PHOTOS, REPO, assert_finds, assert_losses_reach_every_pixel,
                          assert_parity, assert_short_weights_are_refused, assert_unknown_op_is_one_line,
                          assert_vanish_ascent_lowers_the_score, fetched_model, photo)
from undream.engine.context import class_ids
from undream.errors import VictimError
from undream.scene.sources import sequence_from_file
from undream.spec.run import RunConfig
from undream.victims import Target, load_victim
from undream.victims.coco import COCO_LABELS, MODELS

SIZE = MODELS["centernet"].input_size
PERSON = (186, 109, 275, 375)  # the standing woman in person.jpg (640×424)


@pytest.fixture(scope="module")
def model_json() -> Path:
    return fetched_model("centernet")


@pytest.fixture(scope="module")
def victim(model_json: Path):
    return load_victim("coco:centernet", cache_home=CACHE_HOME)


def test_parity_with_tfjs_on_real_photographs(model_json: Path, tmp_path: Path) -> None:
    """The torch port and the official TF.js runtime (CPU backend, under node) agree on
    five real photographs: class scores to 1e-4, box distances to 1e-4 of their range."""
    spec = MODELS["centernet"]
    inputs = {name: (photo(name, SIZE) * 255).permute(0, 2, 3, 1).contiguous() for name in PARITY_PHOTOS}
    assert_parity(model_json, inputs, spec.input, [spec.scores, spec.boxes], {spec.scores}, tmp_path)


@pytest.mark.parametrize("name,cls,least", [("person", "person", 0.5), ("horses", "horse", 0.5),
                                            ("dog", "dog", 0.3), ("bus", "bus", 0.3), ("zidane", "person", 0.3)])
def test_finds_objects_in_real_photographs(victim, name: str, cls: str, least: float) -> None:
    assert_finds(victim, name, cls, least)


def test_predictions_box_the_object_in_input_pixels(victim) -> None:
    """The woman's box is in the photograph's pixels (not the 512² model input's)."""
    x = photo("person")
    pred = victim.predict(x)[0]
    person = next(b for b, lab in zip(pred.boxes, pred.labels) if COCO_LABELS[int(lab)] == "person")
    h, w = x.shape[-2:]
    x0, y0, x1, y1 = person.tolist()
    assert 0 <= x0 < x1 <= w + 5 and 0 <= y0 < y1 <= h + 5
    assert 150 < (x0 + x1) / 2 < 300 and (y1 - y0) > h / 2  # the standing woman, left of centre


@pytest.mark.parametrize("kind,target", [("vanish", Target(label=0, box=PERSON)),
                                         ("mislabel", Target(label=0, target_label=16, box=PERSON)),
                                         ("box", Target(label=0, box=PERSON))])
def test_losses_reach_every_pixel(victim, kind: str, target: Target) -> None:
    assert_losses_reach_every_pixel(victim, kind, target)


def test_vanish_ascent_lowers_the_score(victim) -> None:
    assert_vanish_ascent_lowers_the_score(victim, PERSON)


def test_unknown_op_is_one_line_naming_it(model_json: Path, tmp_path: Path) -> None:
    assert_unknown_op_is_one_line("centernet", model_json, tmp_path, "Relu6")


def test_weights_of_another_shape_are_refused(model_json: Path, tmp_path: Path) -> None:
    assert_short_weights_are_refused("centernet", model_json, tmp_path)


def test_missing_model_says_to_run_setup(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match=r"deploy/setup\.sh"):
        load_victim("coco:centernet", cache_home=str(tmp_path))


def test_unknown_coco_model_lists_the_valid_ones(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match="coco:centernet"):
        load_victim("coco:yolo9000", cache_home=str(tmp_path))


def test_run_check_refuses_a_class_coco_does_not_have(model_json: Path, tmp_path: Path) -> None:
    """Through the command: the bin is no COCO class; refused in one line, nothing written."""
    config = tmp_path / "run.yaml"
    config.write_text(f"name: coco_bin\nscene: {REPO / 'examples' / 'bin_orbit.yaml'}\nvictim: coco:centernet\n"
                      "loss: vanish\nattack: {name: pgd, eps: 16, steps: 1}\nlabel: trash can\n")
    out = tmp_path / "out"
    env = {**os.environ, "XDG_CACHE_HOME": CACHE_HOME}
    done = subprocess.run([str(REPO / ".venv" / "bin" / "undream"), "run", str(config), "--out", str(out),
                           "--check"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode != 0
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "trash can" in lines[0] and "label" in lines[0], done.stderr
    assert not out.exists()


def test_stop_sign_plate_is_cocos_stop_sign_by_default(model_json: Path) -> None:
    """The example stop sign (the plate as the object, the pole an actor) needs no label: the
    built-in part takes the whole's class, and stop_sign reads as COCO's 'stop sign'."""
    seq = sequence_from_file(REPO / "examples" / "stop_sign_street.yaml")
    config = RunConfig.from_json({"name": "s", "scene": "x", "victim": "coco:centernet", "loss": "vanish",
                                  "attack": {"name": "pgd", "eps": 16, "steps": 1}})
    victim = load_victim("coco:centernet", cache_home=CACHE_HOME)
    assert class_ids(config, seq, victim) == (COCO_LABELS.index("stop sign"), None)
