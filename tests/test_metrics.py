"""Metrics: known answers on fixed boxes and labels, JSON out, bad input.

AP expectations are worked by hand for COCO's rule: rank detections by score,
match greedily at IoU >= 0.5, make precision monotone from the right, read it
at the 101 recall points 0, 0.01, ..., 1 and average.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from undream.metrics import (
    Detections,
    GroundTruth,
    MetricsError,
    MetricsReport,
    accuracy,
    attack_success,
    average_precision,
    best_match,
    classification_attack_report,
    classification_report,
    detection_attack_report,
    detection_report,
    is_detected,
    mean_average_precision,
    per_class_ap,
)

CAR, PERSON = 1, 2
OBJ = [10.0, 10.0, 50.0, 50.0]
GT = GroundTruth.single(OBJ, CAR)


def dets(*rows):
    """Detections from (box, score, label) rows."""
    if not rows:
        return Detections.empty()
    return Detections(np.array([r[0] for r in rows], dtype=float),
                      np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))


# --------------------------------------------------------------------------- AP known answers

def test_perfect_predictions_ap_1():
    assert average_precision([dets((OBJ, 0.9, CAR))], [GT], CAR) == pytest.approx(1.0)


def test_empty_predictions_ap_0():
    assert average_precision([dets()], [GT], CAR) == 0.0
    assert mean_average_precision([dets()], [GT]) == 0.0


def test_duplicate_detection_keeps_ap_1():
    # TP at 0.9, duplicate (IoU 0.95 with the same object) at 0.8 = FP ranked below:
    # precision at recall 1 is already 1, so all 101 points read 1.
    d = dets((OBJ, 0.9, CAR), ([11.0, 11.0, 50.0, 50.0], 0.8, CAR))
    assert average_precision([d], [GT], CAR) == pytest.approx(1.0)


def test_false_positive_ranked_first_halves_ap():
    # FP 0.9 then TP 0.8: (recall, precision) = (0, 0), (1, 0.5); monotone envelope
    # is 0.5 everywhere, so every recall point reads 0.5.
    d = dets(([100.0, 100.0, 150.0, 150.0], 0.9, CAR), (OBJ, 0.8, CAR))
    assert average_precision([d], [GT], CAR) == pytest.approx(0.5)


def test_101_point_interpolation_across_frames():
    # Two frames, one object each. Ranked: TP 0.9, FP 0.8, TP 0.7 → recall
    # 0.5, 0.5, 1 and precision 1, 1/2, 2/3; envelope 1, 2/3, 2/3. Recall points
    # 0..0.50 (51 of them) read 1; 0.51..1 (50) read 2/3.
    other = [60.0, 60.0, 90.0, 90.0]
    d = [dets((OBJ, 0.9, CAR), ([100.0, 100.0, 120.0, 120.0], 0.8, CAR)), dets((other, 0.7, CAR))]
    t = [GT, GroundTruth.single(other, CAR)]
    assert average_precision(d, t, CAR) == pytest.approx((51 * 1.0 + 50 * 2 / 3) / 101)


def test_half_recall_reads_51_points():
    # Found in one frame of two: precision 1 up to recall 0.5, nothing beyond → 51/101.
    assert average_precision([dets((OBJ, 0.9, CAR)), dets()], [GT, GT], CAR) == pytest.approx(51 / 101)


def test_iou_threshold_is_inclusive_at_half():
    half = dets(([10.0, 10.0, 50.0, 30.0], 0.9, CAR))  # IoU exactly 0.5
    below = dets(([10.0, 10.0, 50.0, 29.0], 0.9, CAR))
    assert average_precision([half], [GT], CAR) == pytest.approx(1.0)
    assert average_precision([below], [GT], CAR) == 0.0


def test_wrong_class_is_not_a_match():
    d = dets((OBJ, 0.9, PERSON))
    assert per_class_ap([d], [GT]) == {CAR: 0.0, PERSON: None}
    assert mean_average_precision([d], [GT]) == 0.0  # PERSON has no ground truth: left out


def test_map_over_classes():
    p = [60.0, 60.0, 90.0, 90.0]
    t = GroundTruth(np.array([OBJ, p]), np.array([CAR, PERSON]))
    d = dets(([0.0, 0.0, 5.0, 5.0], 0.9, PERSON), (p, 0.8, PERSON), (OBJ, 0.7, CAR))
    assert per_class_ap([d], [t]) == pytest.approx({CAR: 1.0, PERSON: 0.5})
    assert mean_average_precision([d], [t]) == pytest.approx(0.75)
    assert mean_average_precision([d], [t], classes=[CAR]) == pytest.approx(1.0)


def test_no_ground_truth_means_no_ap():
    empty = GroundTruth(np.zeros((0, 4)), [])
    assert average_precision([dets((OBJ, 0.9, CAR))], [empty], CAR) is None
    assert mean_average_precision([dets()], [empty]) is None


def test_frames_without_object_add_false_positives():
    # frame 2 has no ground truth but a confident detection: FP ranked first.
    d = [dets((OBJ, 0.8, CAR)), dets((OBJ, 0.9, CAR))]
    empty = GroundTruth(np.zeros((0, 4)), [])
    assert average_precision(d, [GT, empty], CAR) == pytest.approx(0.5)


def test_accepts_torch_and_prediction_objects():
    class Pred:  # what a victim's DetPrediction looks like
        boxes = torch.tensor([OBJ])
        scores = torch.tensor([0.9])
        labels = torch.tensor([CAR])
    assert average_precision([Pred()], [{"boxes": [OBJ], "labels": [CAR]}], CAR) == pytest.approx(1.0)


def test_best_match_and_is_detected():
    d = dets(([10.0, 10.0, 50.0, 30.0], 0.7, CAR), ([100.0, 100.0, 110.0, 110.0], 0.9, CAR))
    iou, score = best_match(d, GT, CAR)
    assert (iou, score) == (pytest.approx(0.5), 0.7)
    assert is_detected(d, GT, CAR) and not is_detected(d, GT, CAR, iou_threshold=0.6)
    assert best_match(dets(), GT, CAR) == (0.0, None)
    assert not is_detected(d, GT, PERSON)


def test_detection_report_per_frame_and_json(tmp_path):
    r = detection_report([dets((OBJ, 0.9, CAR)), dets()], [GT, GT], CAR)
    assert [f["detected"] for f in r.per_frame] == [True, False]
    assert [f["ap"] for f in r.per_frame] == [pytest.approx(1.0), 0.0]
    assert r.per_frame[1]["score"] is None
    assert r.aggregate["ap"] == pytest.approx(51 / 101)
    assert r.aggregate["detection_rate"] == 0.5
    path = r.save(tmp_path / "det.json")
    loaded = json.loads(path.read_text())
    assert loaded["params"] == {"iou_threshold": 0.5, "object_label": CAR}
    assert loaded["aggregate"]["ap_per_class"] == {"1": pytest.approx(51 / 101)}
    assert MetricsReport.load(path).to_dict() == r.to_dict()


def test_pycocotools_is_silenced(capsys):
    average_precision([dets((OBJ, 0.9, CAR))], [GT], CAR)
    assert capsys.readouterr().out == ""


# --------------------------------------------------------------------------- classification

def test_accuracy_known_answer():
    assert accuracy([0, 1, 2, 1], [0, 1, 1, 1]) == 0.75
    assert accuracy([2, 2], 2) == 1.0
    assert accuracy([], []) is None
    r = classification_report([0, 2], 0)
    assert [f["correct"] for f in r.per_frame] == [True, False]
    assert r.aggregate == {"accuracy": 0.5, "n_frames": 2, "n_correct": 1}


def test_accuracy_takes_predictions_with_label():
    class P:
        def __init__(self, label):
            self.label = label
    assert accuracy([P(1), P(0)], 1) == 0.5


# --------------------------------------------------------------------------- attack success

def test_attack_success_function():
    assert attack_success([True, True, False], [True, False, True]).tolist() == [True, False, False]


def test_classification_attack_known_answer():
    # frame 0: correct → fooled (success); 1: correct → still correct; 2: wrong already (not eligible)
    r = classification_attack_report([0, 0, 1], [2, 0, 2], 0)
    assert [f["success"] for f in r.per_frame] == [True, False, False]
    assert r.aggregate["success_rate"] == 0.5
    assert r.aggregate["success_rate_all"] == pytest.approx(1 / 3)
    assert (r.aggregate["n_eligible"], r.aggregate["n_success"]) == (2, 1)
    targeted = classification_attack_report([0, 0], [2, 1], 0, target_label=2)
    assert targeted.aggregate["success_rate"] == 0.5
    none = classification_attack_report([1], [2], 0)
    assert none.aggregate["success_rate"] is None
    assert json.loads(none.to_json())["aggregate"]["success_rate"] is None


def test_detection_attack_known_answer():
    benign = [dets((OBJ, 0.9, CAR)), dets((OBJ, 0.9, CAR)), dets(), dets((OBJ, 0.9, CAR))]
    adv = [dets(),                                   # vanished: success
           dets(([11.0, 11.0, 50.0, 50.0], 0.6, CAR)),  # still there
           dets(),                                   # missed without attack: not eligible
           dets((OBJ, 0.8, PERSON))]                 # mislabelled: success (untargeted)
    r = detection_attack_report(benign, adv, [GT] * 4, CAR)
    assert [f["success"] for f in r.per_frame] == [True, False, False, True]
    assert r.aggregate["success_rate"] == pytest.approx(2 / 3)
    t = detection_attack_report(benign, adv, [GT] * 4, CAR, target_label=PERSON)
    assert [f["success"] for f in t.per_frame] == [False, False, False, True]
    assert t.aggregate["success_rate"] == pytest.approx(1 / 3)
    assert t.params["target_label"] == PERSON


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("make,pattern", [
    (lambda: Detections(np.zeros((2, 3)), [0.1, 0.2], [0, 0]), r"N×4 boxes .* shape \(2, 3\)"),
    (lambda: Detections(np.array([[5.0, 5.0, 1.0, 9.0]]), [0.5], [0]), "x1 >= x0"),
    (lambda: Detections(np.array([OBJ]), [0.5, 0.6], [0]), r"one entry per box \(1\), got 2"),
    (lambda: Detections(np.array([OBJ]), [float("nan")], [0]), "must be finite"),
    (lambda: Detections(np.array([OBJ]), [0.5], [-1]), r"class ids .* got \[-1.0\]"),
    (lambda: GroundTruth(np.array([OBJ]), [0.5]), "class ids"),
    (lambda: Detections.of({"boxes": [OBJ]}), r"scores: missing"),
])
def test_bad_detections(make, pattern):
    with pytest.raises(MetricsError, match=pattern):
        make()


def test_mismatched_frames():
    with pytest.raises(MetricsError, match="2 frames but ground truth for 1"):
        average_precision([dets(), dets()], [GT], CAR)
    with pytest.raises(MetricsError, match=r"true_labels: need one per frame \(2\), got 3"):
        accuracy([0, 1], [0, 1, 2])
    with pytest.raises(MetricsError, match="iou_threshold"):
        average_precision([dets()], [GT], CAR, iou_threshold=0.0)


def test_report_load_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(MetricsError, match="missing or bad field"):
        MetricsReport.load(bad)
    with pytest.raises(MetricsError, match="cannot read"):
        MetricsReport.load(tmp_path / "none.json")
