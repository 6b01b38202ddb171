"""The YOLO family (issue 23): undream's plain-torch YOLO-style detector, NMS, the dense losses,
the ultralytics output layout, loading and its one-line errors.

Everything runs on tiny models and 32–96 px images with one torch thread. Nothing here runs
ultralytics itself (it is not installed): its output layout is reproduced by :class:`AsUltralytics`
from the plain-torch detector's candidates, and its package by a stand-in module in ``sys.modules``.
"""
from __future__ import annotations

import json
from dataclasses import asdict
import re
import sys
import types

import numpy as np
import pytest
import torch

from undream.errors import VictimError
from undream.metrics import detection_report
from undream.training.yolo import YoloLossConfig, build_yolo, synthetic_squares, yolo_loss
from undream.victims import Target, load_victim, losses, registry
from undream.victims.dense import DenseDetector
from undream.victims.nms import batched_nms, nms, select_detections
from undream.victims.preprocess import PreprocessConfig
from undream.victims.yolo import YoloConfig, YoloNet, anchor_points
from undream.victims.yolo_load import load_yolo_victim

LABELS = ("red", "green", "blue")
SIZE = 64
PRE = PreprocessConfig(size=(SIZE, SIZE), mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25))


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _tiny(seed: int = 0, **kw) -> YoloNet:
    torch.manual_seed(seed)
    return YoloNet(YoloConfig(labels=LABELS, widths=(8, 12, 16, 24, 32), neck=16, head=16, **kw))


def _normalise(x: torch.Tensor) -> torch.Tensor:
    return (x - 0.5) / 0.25


@pytest.fixture(scope="module")
def trained():
    """A tiny detector trained 150 steps on synthetic squares (a few seconds on one thread), and
    the loss on a fixed batch before and after."""
    gen = torch.Generator().manual_seed(0)
    images, boxes, labels = synthetic_squares(96, SIZE, gen, max_objects=2)
    model = _tiny()
    fixed = slice(0, 32)
    with torch.no_grad():
        before, _ = yolo_loss(model(_normalise(images[fixed])), boxes[fixed], labels[fixed], (SIZE, SIZE))
    opt = torch.optim.AdamW(model.parameters(), 3e-3)
    model.train()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one thread: its floats do not depend on how many cores the machine has
    try:
        for _ in range(150):
            idx = torch.randint(0, len(images), (16,), generator=gen)
            loss, _ = yolo_loss(model(_normalise(images[idx])), boxes[idx], labels[idx], (SIZE, SIZE))
            opt.zero_grad()
            loss.backward()
            opt.step()
    finally:
        torch.set_num_threads(threads)
    model.eval()
    with torch.no_grad():
        after, _ = yolo_loss(model(_normalise(images[fixed])), boxes[fixed], labels[fixed], (SIZE, SIZE))
    return {"model": model, "before": float(before), "after": float(after)}


def _square(label: int = 0, box=(18, 14, 46, 42), seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, SIZE, SIZE, generator=g) * 0.5 + 0.25
    x0, y0, x1, y1 = (int(v) for v in box)
    x[0, :, y0:y1, x0:x1] = torch.tensor(((1.0, 0.1, 0.1), (0.1, 0.9, 0.1), (0.1, 0.2, 1.0))[label])[:, None, None]
    return x


class AsUltralytics(torch.nn.Module):
    """The plain-torch detector's candidates as an ultralytics ``DetectionModel`` returns them in
    eval mode: ``(B×(4 + C)×N, feature maps)``, centre-xywh pixels and sigmoid probabilities."""

    def __init__(self, model: YoloNet) -> None:
        super().__init__()
        self.inner = model

    def forward(self, x):
        out = self.inner(x)
        b = out[..., :4]
        cxcywh = torch.cat(((b[..., :2] + b[..., 2:]) / 2, b[..., 2:] - b[..., :2]), -1)
        return torch.cat((cxcywh, out[..., 4:].sigmoid()), -1).transpose(1, 2), [x]


# --------------------------------------------------------------------------- the model

@pytest.mark.parametrize("size,n", [(64, 8 * 8 + 4 * 4 + 2 * 2), (96, 12 * 12 + 6 * 6 + 3 * 3)])
def test_output_shapes_at_two_sizes(size, n):
    out = _tiny()(torch.rand(2, 3, size, size))
    assert out.shape == (2, n, 4 + len(LABELS))
    boxes = out[..., :4]
    assert bool((boxes[..., 2:] > boxes[..., :2]).all()) and bool(torch.isfinite(out).all())


def test_anchor_points_order_and_input_rule():
    points, strides = anchor_points(64, 64)
    assert points[:3].tolist() == [[4, 4], [12, 4], [20, 4]] and points[8].tolist() == [4, 12]
    assert points[64].tolist() == [8, 8] and points[-1].tolist() == [48, 48]
    assert strides.tolist() == [8.0] * 64 + [16.0] * 16 + [32.0] * 4
    with pytest.raises(VictimError, match=r"multiples of 32, got 48×64"):
        _tiny()(torch.rand(1, 3, 48, 64))
    with pytest.raises(VictimError, match=r"yolo.input_size: must be a multiple of 32, got 40"):
        YoloConfig(labels=LABELS, input_size=40)


def test_save_and_load_round_trip(tmp_path):
    model = _tiny().eval()
    model.save_pretrained(tmp_path / "m")
    cfg = json.loads((tmp_path / "m" / "config.json").read_text())
    assert cfg["model_type"] == "undream_yolo" and cfg["id2label"] == {"0": "red", "1": "green", "2": "blue"}
    victim = load_victim(str(tmp_path / "m"))
    assert isinstance(victim, DenseDetector) and victim.labels == list(LABELS) and victim.task == "detection"
    x = torch.rand(1, 3, 32, 48)  # resized to the config's 64×64 (no preprocessor_config.json)
    with torch.no_grad():
        expect = model(torch.nn.functional.interpolate(x, size=(64, 64), mode="bilinear", align_corners=False))
    assert torch.allclose(victim.forward_raw(x).boxes, expect[..., :4], atol=1e-5)


# --------------------------------------------------------------------------- NMS

def test_nms_known_answer():
    """Two classes: B overlaps A (IoU 81/119 = 0.68) and goes; C overlaps A more (IoU 0.82) but is
    of the other class and stays; D stands alone; E too, but scores under the threshold."""
    boxes = torch.tensor([[0, 0, 10, 10], [1, 1, 11, 11], [1, 0, 11, 10], [20, 20, 30, 30],
                          [40, 40, 50, 50]], dtype=torch.float32)
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.1])
    labels = torch.tensor([0, 0, 1, 0, 0])
    assert batched_nms(boxes, scores, labels, 0.5).tolist() == [0, 2, 3, 4]
    assert nms(boxes, scores, 0.5).tolist() == [0, 3, 4]  # class-blind: C goes too (IoU 0.82 with A)
    assert batched_nms(boxes, scores, labels, 0.7).tolist() == [0, 1, 2, 3, 4]  # 0.68 < 0.7
    probs = torch.zeros(5, 2)
    probs[torch.arange(5), labels] = scores
    b, s, lab = select_detections(boxes, probs, 0.2, 0.5, max_detections=10)
    assert b.tolist() == boxes[[0, 2, 3]].tolist() and s.tolist() == pytest.approx([0.9, 0.7, 0.6])
    assert lab.tolist() == [0, 1, 0]
    assert select_detections(boxes, probs, 0.2, 0.5, max_detections=2)[1].tolist() == pytest.approx([0.9, 0.7])
    assert select_detections(boxes, probs, 0.95, 0.5, 10)[0].shape == (0, 4)


def test_nms_bad_shapes():
    with pytest.raises(VictimError, match=r"nms: boxes must be N×4 and scores N, got \(3, 5\) and \(3,\)"):
        nms(torch.zeros(3, 5), torch.zeros(3), 0.5)


# --------------------------------------------------------------------------- training

def test_a_tiny_training_run_lowers_the_loss(trained):
    assert trained["after"] < 0.5 * trained["before"], trained


def test_assignment_gives_every_box_positives():
    boxes = torch.tensor([[[0, 0, 6, 6], [16, 16, 48, 48]]], dtype=torch.float32)  # one under a stride
    labels = torch.tensor([[1, 2]])
    out = _tiny()(torch.rand(1, 3, 64, 64))
    loss, parts = yolo_loss(out, boxes, labels, (64, 64), YoloLossConfig())
    assert torch.isfinite(loss) and parts["positives"] >= 2
    with pytest.raises(VictimError, match=r"true boxes must be B×M×4 and labels B×M"):
        yolo_loss(out, boxes[0], labels, (64, 64))


def test_trained_detector_finds_the_square(trained):
    victim = DenseDetector(trained["model"], LABELS, PRE)
    for label in range(3):
        pred = victim.predict(_square(label))[0]
        assert len(pred.scores) and int(pred.labels[0]) == label, (label, pred)
        iou, _ = losses.box_iou_giou(pred.boxes[0], torch.tensor([18.0, 14, 46, 42]))
        assert float(iou) > 0.5, pred.boxes[0]


# --------------------------------------------------------------------------- dense losses

@pytest.mark.parametrize("kind,with_box", [("vanish", True), ("mislabel", True), ("box", True),
                                           ("vanish", False), ("mislabel", False)])
def test_dense_loss_gradients_are_finite(trained, kind, with_box):
    victim = DenseDetector(trained["model"], LABELS, PRE)
    x = _square(0).repeat(2, 1, 1, 1).requires_grad_(True)
    target = Target(0, target_label=2, box=(18, 14, 46, 42) if with_box else None)
    values, preds = victim.loss_and_predict(x, target, kind)
    assert values.shape == (2,) and len(preds) == 2
    (g,) = torch.autograd.grad(values.sum(), x)
    assert bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0


STEPS = 10


def _top_score(victim: DenseDetector, x: torch.Tensor, label: int) -> float:
    with torch.no_grad():
        return float(victim.forward_raw(x).log_probs[..., label].exp().max())


@pytest.mark.parametrize("reduce", ["mean", "max"])
def test_vanish_steps_lower_the_objects_top_score(trained, reduce):
    victim = DenseDetector(trained["model"], LABELS, PRE, vanish_reduce=reduce)
    x = _square(0)
    target = Target(0, box=(18, 14, 46, 42))
    scores = [_top_score(victim, x, 0)]
    for _ in range(2 * STEPS):  # PGD ascent on the loss, 2/255 per step
        x = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(victim.loss(x, target, "vanish"), x)
        x = (x + 2 / 255 * g.sign()).clamp(0, 1).detach()
        scores.append(_top_score(victim, x, 0))
    # 20 steps: after 10, max read 0.449 on one machine and 0.636 on another (an AMD EPYC), the tiny
    # model's training differing in its floats; after 20, measured on the EPYC: 0.993 → 0.038 (mean), 0.028 (max)
    assert scores[0] > 0.9 and scores[-1] < 0.6 * scores[0], scores


def test_dense_weights_known_answer():
    """Two candidates on the box (one by IoU, one by its cell centre), one off it."""
    log_probs = torch.tensor([[[0.8, 0.1], [0.2, 0.6], [0.9, 0.9]]]).log()
    boxes = torch.tensor([[[0.1, 0.1, 0.5, 0.5], [0.6, 0.6, 0.7, 0.7], [0.8, 0.8, 1.0, 1.0]]])
    points = torch.tensor([[0.3, 0.3], [0.35, 0.35], [0.9, 0.9]])
    truth = torch.tensor([[0.1, 0.1, 0.5, 0.5]])
    w = losses.dense_weights(log_probs, boxes, 0, truth, points)
    assert w[0].tolist() == pytest.approx([0.8 / 1.4, 0.6 / 1.4, 0.0])  # each weighted by its best score
    w = losses.dense_weights(log_probs, boxes, 0, truth, None)  # IoU alone
    assert w[0].tolist() == pytest.approx([1.0, 0.0, 0.0])
    w = losses.dense_weights(log_probs, boxes, 0, torch.full((1, 4), float("nan")), points)
    assert w[0].tolist() == pytest.approx([0.8 / 1.9, 0.2 / 1.9, 0.9 / 1.9])  # no box: p(true class)


# --------------------------------------------------------------------------- the ultralytics layout

def test_ultralytics_layout_gives_the_native_detections_losses_and_metrics(trained):
    native = DenseDetector(trained["model"], LABELS, PRE)
    ultra = DenseDetector(AsUltralytics(trained["model"]), LABELS, PRE, output_format="ultralytics")
    x = torch.cat([_square(0), _square(2, box=(8, 30, 30, 60), seed=2), torch.rand(1, 3, SIZE, SIZE)])
    targets = [Target(0, 1, (18, 14, 46, 42)), Target(2, 0, (8, 30, 30, 60)), Target(1, 2, (0, 0, 20, 20))]
    for kind in ("vanish", "mislabel", "box"):
        xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
        la, pa = native.loss_and_predict(xa, targets, kind)
        lb, pb = ultra.loss_and_predict(xb, targets, kind)
        assert torch.allclose(la, lb, atol=1e-5, rtol=1e-4), (kind, la, lb)
        ga, = torch.autograd.grad(la.sum(), xa)
        gb, = torch.autograd.grad(lb.sum(), xb)
        assert torch.allclose(ga, gb, atol=1e-6, rtol=1e-3), kind
    assert native.forward_raw(x).points is not None and ultra.forward_raw(x).points is not None
    for a, b in zip(native.predict(x, threshold=0.0), ultra.predict(x, threshold=0.0)):
        assert a.labels.tolist() == b.labels.tolist() and len(a.scores) > 0
        assert torch.allclose(a.boxes, b.boxes, atol=1e-4) and torch.allclose(a.scores, b.scores, atol=1e-6)
    truths = [{"boxes": [t.box], "labels": [t.label]} for t in targets]
    ra = detection_report(native.predict(x), truths, object_label=0).aggregate
    rb = detection_report(ultra.predict(x), truths, object_label=0).aggregate
    assert ra == rb and ra["ap"] == pytest.approx(1.0) and ra["detection_rate"] == 1.0


def test_ultralytics_layout_checked():
    ultra = DenseDetector(AsUltralytics(_tiny()), ["a", "b"], PRE, output_format="ultralytics")
    with pytest.raises(VictimError, match=r"must be B×\(4 \+ 2\)×N .*got \(1, 7, 84\)"):
        ultra.predict(torch.rand(1, 3, 64, 64))
    with pytest.raises(VictimError, match="output_format must be one of native, ultralytics, got 'onnx'"):
        DenseDetector(_tiny(), LABELS, PRE, output_format="onnx")


class _FakeYOLO:
    """Stands in for ``ultralytics.YOLO``: a detector over LABELS made of the tiny plain-torch model."""

    task = "detect"

    def __init__(self, path: str) -> None:
        if open(path, "rb").read(4) != b"YOLO":
            raise RuntimeError("invalid load key, '\\x8f'.\nmore lines")
        self.model = AsUltralytics(_tiny())
        self.model.args = {"imgsz": 64}
        self.model.stride = torch.tensor([8.0, 16.0, 32.0])
        self.names = dict(enumerate(LABELS))


@pytest.fixture()
def fake_ultralytics(monkeypatch):
    module = types.ModuleType("ultralytics")
    module.YOLO = _FakeYOLO
    monkeypatch.setitem(sys.modules, "ultralytics", module)
    return module


def test_pt_file_loads_through_ultralytics(fake_ultralytics, tmp_path):
    (tmp_path / "yolo11n.pt").write_bytes(b"YOLO weights")
    victim = load_victim(str(tmp_path / "yolo11n.pt"))
    assert isinstance(victim, DenseDetector) and victim.output_format == "ultralytics"
    assert victim.labels == list(LABELS) and victim.preprocess_config.size == (64, 64)
    x = torch.rand(1, 3, 80, 80)
    assert victim.forward_raw(x).points is not None and len(victim.predict(x)) == 1
    (tmp_path / "bad.pt").write_bytes(b"\x8f\x01 random bytes")
    with pytest.raises(VictimError) as err:
        load_victim(str(tmp_path / "bad.pt"))
    assert str(err.value) == (f"victim '{tmp_path / 'bad.pt'}': ultralytics cannot load it "
                              "(RuntimeError: invalid load key, '\\x8f'.)")
    fake_ultralytics.YOLO = type("Cls", (_FakeYOLO,), {"task": "classify"})
    with pytest.raises(VictimError, match=r"an ultralytics 'classify' model, not a detector"):
        load_victim(str(tmp_path / "yolo11n.pt"))


# --------------------------------------------------------------------------- bad inputs, one line each

def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    return text


def test_pt_file_without_ultralytics(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ultralytics", None)  # import ultralytics raises ImportError
    (tmp_path / "yolov8n.pt").write_bytes(b"\x80\x02 anything")
    with pytest.raises(VictimError) as err:
        load_victim(str(tmp_path / "yolov8n.pt"))
    assert "the ultralytics package is not installed" in _one_line(err)
    assert "requires torchvision" in str(err.value)
    with pytest.raises(VictimError, match="no such file"):
        load_victim(str(tmp_path / "missing.pt"))


def test_folders_and_files_that_are_not_detectors(tmp_path):
    cls = tmp_path / "classifier"
    cls.mkdir()
    (cls / "config.json").write_text(json.dumps({"model_type": "resnet", "num_labels": 3}))
    with pytest.raises(VictimError, match=r"model_type 'resnet' is not an undream YOLO detector"):
        load_yolo_victim(cls)
    good = tmp_path / "good"
    _tiny().save_pretrained(good)
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "config.json").write_text((good / "config.json").read_text())
    (junk / "model.safetensors").write_bytes(bytes(range(256)) * 8)
    with pytest.raises(VictimError) as err:
        load_victim(str(junk))
    assert "cannot read model.safetensors" in _one_line(err)
    other = tmp_path / "other"
    YoloNet(YoloConfig(labels=LABELS)).save_pretrained(other)
    (junk / "model.safetensors").write_bytes((other / "model.safetensors").read_bytes())
    with pytest.raises(VictimError) as err:
        load_victim(str(junk))
    assert "model.safetensors does not fit its config.json" in _one_line(err)
    (tmp_path / "weights.bin").write_bytes(b"\x00\x01random")
    with pytest.raises(VictimError, match=r"is a file; pass a save_pretrained or undream YOLO folder"):
        load_victim(str(tmp_path / "weights.bin"))
    with pytest.raises(VictimError, match="does detection, cannot do classification"):
        load_victim(str(good), task="classification")


def test_class_names_the_model_does_not_have(tmp_path):
    from undream.engine.context import class_id

    victim = DenseDetector(_tiny(), LABELS, PRE, name="tiny")
    assert class_id(victim, "Green", "label") == 1
    with pytest.raises(VictimError) as err:
        class_id(victim, "cat", "target_label")
    assert _one_line(err) == "target_label: 'cat' is not one of tiny's classes (red, green, blue)"
    with pytest.raises(VictimError, match=r"target.target_label: 7 is not a class of victim 'tiny'"):
        victim.loss(torch.rand(1, 3, 64, 64), Target(0, target_label=7), "mislabel")
    with pytest.raises(VictimError, match=r"loss kind 'box': needs Target.box"):
        victim.loss(torch.rand(1, 3, 64, 64), Target(0), "box")


def test_bundled_yolo_absent_and_present(monkeypatch, tmp_path):
    monkeypatch.setattr(registry, "BUNDLED_DIR", tmp_path)
    with pytest.raises(VictimError) as err:
        load_victim("bundled:yolo")
    assert _one_line(err).startswith("bundled victim 'yolo': its weights are not present")
    assert "--arch yolo" in str(err.value)
    _tiny().save_pretrained(tmp_path / "yolo")
    victim = load_victim("bundled:yolo")
    assert isinstance(victim, DenseDetector) and victim.labels == list(LABELS)
    with pytest.raises(VictimError, match="does detection, cannot do classification"):
        load_victim("bundled:yolo", task="classification")


# --------------------------------------------------------------------------- undream victims train --arch yolo

def _synthetic_dataset(folder, n: int, seed: int):
    """A dataset folder in make-dataset's layout, of synthetic squares (classes 0-2 of CLASSES)."""
    from PIL import Image

    from undream.training.dataset import CLASSES, sample_params

    gen = torch.Generator().manual_seed(seed)
    images, boxes, labels = synthetic_squares(n, SIZE, gen, max_objects=1)
    (folder / "images").mkdir(parents=True)
    lines = []
    for i in range(n):
        Image.fromarray((images[i].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(
            folder / "images" / f"{i:05d}.png")
        lab = int(labels[i, 0])
        drawn = sample_params(np.random.default_rng([seed, i]), "train", lab)  # what a render would record
        params = {**asdict(drawn), "environment": drawn.environment.to_json()}
        lines.append(json.dumps({"file": f"images/{i:05d}.png", "index": i, "label": lab, "name": CLASSES[lab],
                                 "box": boxes[i, 0].tolist(), "params": params}))
    (folder / "labels.jsonl").write_text("\n".join(lines) + "\n")
    (folder / "metadata.json").write_text(json.dumps({
        "classes": list(CLASSES), "command": "synthetic squares (tests/test_yolo.py)",
        "config": {"n": n, "seed": seed, "size": SIZE, "spp": 1, "split": "train"}}))
    return folder


def test_victims_train_arch_yolo_end_to_end(tmp_path):
    from click.testing import CliRunner

    from undream.cli.victims import victims

    data, test = _synthetic_dataset(tmp_path / "data", 24, 0), _synthetic_dataset(tmp_path / "test", 8, 1)
    out = tmp_path / "out"
    res = CliRunner().invoke(victims, ["train", "--task", "detection", "--arch", "yolo", "--data", str(data),
                                       "--test", str(test), "--out", str(out), "--epochs", "1",
                                       "--threads", "1"])
    assert res.exit_code == 0, res.output
    assert {p.name for p in out.iterdir()} >= {"config.json", "model.safetensors", "preprocessor_config.json",
                                               "training.json", "MODEL_CARD.md"}
    record = json.loads((out / "training.json").read_text())
    assert record["config"]["arch"] == "yolo" and record["defaults"]["lr"] == 2e-3
    assert 0.0 <= record["test"]["ap50"] <= 1.0
    assert (out / "MODEL_CARD.md").read_text().startswith("# bundled:yolo — YOLO-style one-stage detector")
    victim = load_victim(str(out))
    assert isinstance(victim, DenseDetector) and victim.preprocess_config.mean == (0.485, 0.456, 0.406)
    for args, message in ((["--task", "classification", "--arch", "yolo"], "classification trains resnet, got 'yolo'"),
                          (["--task", "detection", "--arch", "yolo", "--backbone", str(data)],
                           "the yolo detector trains from scratch")):
        res = CliRunner().invoke(victims, ["train", *args, "--data", str(data), "--test", str(test),
                                           "--out", str(tmp_path / "new")])
        assert res.exit_code == 2 and res.output.strip().count("\n") == 0 and message in res.output, res.output


def test_the_attack_engine_runs_a_dense_victim(trained):
    """The engine's victim pass (loss, image gradient, prediction record) and its judge (AP@0.5) on a
    DenseDetector, as a run with ``victim: bundled:yolo`` or a YOLO folder would call them."""
    from types import SimpleNamespace

    from undream.engine.algorithm import judge
    from undream.engine.job import victim_pass

    victim = DenseDetector(trained["model"], LABELS, PRE)
    targets = [Target(0, box=(18, 14, 46, 42)), Target(0, box=(8, 30, 30, 60))]
    ctx = SimpleNamespace(victim=victim, targets=targets, config=SimpleNamespace(loss="vanish", seed=0),
                          frame_indices=[3, 4],
                          sequence=SimpleNamespace(frames=[SimpleNamespace(index=3), SimpleNamespace(index=4)]))
    frames = [_square(0, box=t.box, seed=s)[0].permute(1, 2, 0).numpy() for t, s in zip(targets, (1, 2))]
    values, grads, records = victim_pass(ctx, [0, 1], frames)
    assert len(values) == 2 and all(-1.0 <= v < -0.5 for v in values), values  # the squares are found
    assert grads[0].shape == (SIZE, SIZE, 3) and all(bool(abs(g).sum() > 0) for g in grads)
    assert [r["detected"] for r in records] == [True, True] and records[0]["score"] > 0.5
    verdict = judge(ctx, victim.predict(torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2)))
    assert verdict["metric"] == "ap50" and verdict["value"] == pytest.approx(1.0)
    assert [r["frame"] for r in verdict["per_frame"]] == [3, 4]


@pytest.mark.parametrize("kind", ["vanish", "mislabel", "box"])
def test_dense_loss_gradient_matches_finite_differences(trained, kind):
    """In float64, the image gradient's directional derivative equals a central difference of the
    loss with the weights held where they are at the image: weights are detached by design (they
    select and weigh candidates; their own change with the image is no part of the gradient)."""
    import copy

    victim = DenseDetector(copy.deepcopy(trained["model"]).double(), LABELS, PRE)
    x = _square(0).double()
    target = Target(0, target_label=1, box=(18, 14, 46, 42))
    y, t = torch.tensor([0]), torch.tensor([1])
    truth = torch.tensor([target.box], dtype=torch.float64) / SIZE
    with torch.no_grad():
        raw = victim.forward_raw(x)
        w = losses.dense_weights(raw.log_probs, raw.boxes_xyxy, y, truth, raw.points_norm)

    def fixed(image):  # the loss with the weights w
        out = victim.forward_raw(image)
        if kind == "vanish":
            return losses.det_vanish(out.log_probs, y, w)
        if kind == "mislabel":
            return losses.det_mislabel(out.log_probs, t, w)
        return losses.det_box(out.boxes_xyxy, truth, w)

    d = torch.randn(x.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    xg = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(victim.loss(xg, target, kind), xg)
    h = 1e-6
    with torch.no_grad():
        fd = (fixed(x + h * d) - fixed(x - h * d)) / (2 * h)
    assert float(fd) == pytest.approx(float((g * d).sum()), rel=1e-5, abs=1e-9)


def test_dense_detector_settings_checked():
    for kw, message in (({"iou_threshold": 1.5}, "iou_threshold must be in [0, 1], got 1.5"),
                        ({"min_iou": -0.1}, "min_iou must be in [0, 1], got -0.1"),
                        ({"max_detections": 0}, "max_detections must be an integer >= 1, got 0"),
                        ({"score_threshold": 2.0}, "score_threshold must be in [0, 1], got 2.0"),
                        ({"vanish_reduce": "sum"}, "vanish_reduce must be 'mean' or 'max', got 'sum'")):
        with pytest.raises(VictimError, match=re.escape(message)):
            DenseDetector(_tiny(), LABELS, PRE, **kw)
    with pytest.raises(VictimError, match=r"model output must be a tensor of candidates \(native layout\), got dict"):
        DenseDetector(_DictOut(), LABELS, PRE).predict(torch.rand(1, 3, 64, 64))


class _DictOut(torch.nn.Module):
    def forward(self, x):
        return {"one2one": x}


# --------------------------------------------------------------------------- the shipped bundled:yolo, as a user runs it

def test_undream_run_against_the_shipped_yolo_raises_its_vanish_loss(tmp_path):
    """`undream run` with ``victim: bundled:yolo`` (the dense loss through the whole iteration): the
    run records AP@0.5 on attacked and held-out frames, and PGD raises the loss it maximises."""
    import subprocess
    from pathlib import Path

    from farm_support import make_scene, run_config, write_yaml

    root = Path(__file__).resolve().parents[1]
    scene = make_scene(tmp_path / "scene", n_frames=4, size=32)
    cfg = run_config(scene, "bundled:yolo", name="yolo", steps=4, loss="vanish")  # ε 32
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(tmp_path / "run.yaml", cfg)),
                          "--out", str(out), "--no-progress"], capture_output=True, text=True, cwd=root,
                         env={**__import__("os").environ, "HF_HUB_OFFLINE": "1"})
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["attacked"]["benign"]["metric"] == "ap50" and results["held_out"]["frames"] == [3]
    losses = results["loss_per_iteration"]
    assert len(losses) == 4 and losses[-1] > losses[0]
