"""Victims: preprocessing, losses, adapters (plain torch and Hugging Face).

The Hugging Face models are tiny and randomly initialised, built from config
classes and saved to a tmp folder, then loaded by path: no network, no
downloaded weights.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from farm_support import make_scene, make_victim, run_config, write_yaml
from undream.errors import VictimError
from undream.store import open_store
from undream.victims import (
    Classifier,
    Detector,
    PreprocessConfig,
    Target,
    check_images,
    load_victim,
    preprocess_images,
)
from undream.victims import losses, registry

LABELS = ["car", "person", "sign"]
H, W = 40, 56
BOX = (8.0, 6.0, 40.0, 30.0)  # xyxy pixels of a 40×56 image


# --------------------------------------------------------------------------- fixtures

def _tiny_resnet(**kw):
    from transformers import ResNetConfig
    return ResNetConfig(embedding_size=8, hidden_sizes=[8, 16], depths=[1, 1], **kw)


def _labels_kw():
    return {"id2label": dict(enumerate(LABELS)), "label2id": {n: i for i, n in enumerate(LABELS)}}


def _detr_kw():
    return dict(use_timm_backbone=False, use_pretrained_backbone=False,
                backbone_config=_tiny_resnet(out_features=["stage2"]), d_model=32,
                encoder_layers=1, decoder_layers=1, encoder_attention_heads=2,
                decoder_attention_heads=2, encoder_ffn_dim=32, decoder_ffn_dim=32,
                num_queries=10, **_labels_kw())


def _save(model, path, processor):
    model.save_pretrained(path)
    (path / "preprocessor_config.json").write_text(json.dumps(processor))
    return str(path)


@pytest.fixture(scope="module")
def hf_paths(tmp_path_factory):
    import transformers as T
    root = tmp_path_factory.mktemp("hf")
    torch.manual_seed(0)
    cls = T.ResNetForImageClassification(_tiny_resnet(**_labels_kw()))
    detr = T.DetrForObjectDetection(T.DetrConfig(**_detr_kw()))
    cond = T.ConditionalDetrForObjectDetection(T.ConditionalDetrConfig(**_detr_kw()))
    convnext = {"size": {"shortest_edge": 32}, "crop_pct": 0.875, "do_normalize": True,
                "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]}
    detr_proc = {"size": {"shortest_edge": 48, "longest_edge": 64}, "do_normalize": True,
                 "image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}
    return {"classifier": _save(cls, root / "cls", convnext),
            "detr": _save(detr, root / "detr", detr_proc),
            "cond_detr": _save(cond, root / "cond", detr_proc)}


class TinyNet(torch.nn.Module):
    """A conv net with a classification head and a DETR-style detection head."""

    def __init__(self, classes: int, queries: int = 0, no_object: bool = True) -> None:
        super().__init__()
        self.queries = queries
        self.conv = torch.nn.Conv2d(3, 8, 3, padding=1)
        width = classes + (1 if queries and no_object else 0)
        self.cls = torch.nn.Linear(8, width * max(queries, 1))
        self.box = torch.nn.Linear(8, 4 * queries) if queries else None

    def forward(self, x):
        f = torch.tanh(self.conv(x)).mean((2, 3))
        if not self.queries:
            return self.cls(f)
        b = x.shape[0]
        return (self.cls(f).view(b, self.queries, -1),
                torch.sigmoid(self.box(f)).view(b, self.queries, 4))


@pytest.fixture(scope="module")
def victims(hf_paths, monkeypatch_module):
    torch.manual_seed(0)
    pre = PreprocessConfig(size=(32, 32), mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25))
    return {
        "torch_classifier": Classifier(TinyNet(3), LABELS, pre),
        "torch_detector": Detector(TinyNet(3, queries=6), LABELS, pre),
        "torch_detector_sigmoid": Detector(TinyNet(3, queries=6, no_object=False), LABELS, pre),
        "hf_classifier": load_victim(hf_paths["classifier"]),
        "hf_detr": load_victim(hf_paths["detr"]),
        "hf_conditional_detr": load_victim(hf_paths["cond_detr"], task="detection"),
    }


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    mp.setenv("HF_HUB_OFFLINE", "1")
    yield mp
    mp.undo()


def _images(batch: int = 2, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 3, H, W, generator=g)


# --------------------------------------------------------------------------- gradients

CASES = [(name, kind) for name in ("torch_classifier", "hf_classifier")
         for kind in ("ce", "targeted_ce", "dlr")]
CASES += [(name, kind) for name in ("torch_detector", "torch_detector_sigmoid", "hf_detr",
                                    "hf_conditional_detr")
          for kind in ("vanish", "mislabel", "box")]


@pytest.mark.parametrize("name,kind", CASES)
def test_gradient_is_finite_and_nonzero(victims, name, kind):
    victim = victims[name]
    x = _images().requires_grad_(True)
    loss = victim.loss(x, Target(label=0, target_label=2, box=BOX), kind)
    assert loss.ndim == 0 and torch.isfinite(loss)
    (grad,) = torch.autograd.grad(loss, x)
    assert grad.shape == x.shape
    assert torch.isfinite(grad).all()
    assert grad.abs().sum() > 0


@pytest.mark.parametrize("name", ["torch_detector", "hf_detr", "hf_conditional_detr"])
@pytest.mark.parametrize("kind", ["vanish", "mislabel"])
def test_detection_gradient_without_box(victims, name, kind):
    x = _images().requires_grad_(True)
    loss = victims[name].loss(x, Target(label=1, target_label=2), kind)
    (grad,) = torch.autograd.grad(loss, x)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_models_frozen_and_in_eval(victims):
    for v in victims.values():
        assert not v.module.training
        assert not any(p.requires_grad for p in v.module.parameters())


def test_per_image_targets(victims):
    v = victims["hf_detr"]
    x = _images(2)
    ts = [Target(0, box=BOX), Target(1)]  # one with a box, one without
    assert torch.isfinite(v.loss(x, ts, "vanish"))
    with pytest.raises(VictimError, match="one per image"):
        v.loss(x, [Target(0)], "vanish")


# --------------------------------------------------------------------------- one pass per batch

@pytest.fixture(scope="module")
def batch_victims(victims):
    """Victims built here (torch and tiny HF) and the bundled classifier."""
    bundled = load_victim("bundled:classifier", device="cpu", task="classification")
    return {**victims, "bundled_classifier": bundled}


BATCH_CASES = [(name, kind) for name in ("torch_classifier", "hf_classifier", "bundled_classifier")
               for kind in ("ce", "targeted_ce", "dlr")]
BATCH_CASES += [(name, kind) for name in ("torch_detector", "torch_detector_sigmoid", "hf_detr")
                for kind in ("vanish", "mislabel", "box")]
BOXES = [BOX, (4.0, 4.0, 30.0, 36.0), (20.0, 10.0, 52.0, 38.0)]


def _targets(victim, batch: int = 3) -> list[Target]:
    """A different label, target label and box per image."""
    c = victim.num_classes
    return [Target(i % c, target_label=(i + 1) % c, box=BOXES[i % len(BOXES)]) for i in range(batch)]


@pytest.mark.parametrize("name,kind", BATCH_CASES)
def test_per_image_losses_equal_each_image_alone(batch_victims, name, kind):
    v = batch_victims[name]
    x, ts = _images(3, seed=1), _targets(batch_victims[name])
    per = v.losses(x, ts, kind)
    assert per.shape == (3,)
    alone = torch.stack([v.losses(x[i:i + 1], ts[i], kind)[0] for i in range(3)])
    assert torch.allclose(per, alone, rtol=1e-5, atol=1e-7)
    assert torch.allclose(per.mean(), v.loss(x, ts, kind), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name,kind", BATCH_CASES)
def test_batched_gradient_equals_per_image_gradient(batch_victims, name, kind):
    """d losses(X).sum() / dX, image by image, is the gradient of loss(x_i) alone."""
    v = batch_victims[name]
    x, ts = _images(3, seed=1).requires_grad_(True), _targets(v)
    (g,) = torch.autograd.grad(v.losses(x, ts, kind).sum(), x)
    scale = float(g.abs().max())  # one image may have none: 3-class DLR is 1 when y is the least logit
    assert scale > 0
    for i in range(3):
        xi = x[i:i + 1].detach().clone().requires_grad_(True)
        (gi,) = torch.autograd.grad(v.loss(xi, ts[i], kind), xi)
        assert float((g[i] - gi[0]).abs().max()) <= 1e-6 * scale


def _same_predictions(a, b) -> None:
    assert len(a) == len(b)
    for p, q in zip(a, b):
        if hasattr(p, "probs"):
            assert p.label == q.label and torch.allclose(p.probs, q.probs, atol=1e-6)
            assert not p.probs.requires_grad
        else:
            assert torch.equal(p.labels, q.labels)
            assert torch.allclose(p.scores, q.scores, atol=1e-6)
            assert torch.allclose(p.boxes, q.boxes, atol=1e-5)
            assert not (p.scores.requires_grad or p.boxes.requires_grad)


@pytest.mark.parametrize("name,kind", BATCH_CASES)
def test_loss_and_predict_runs_the_model_once(batch_victims, name, kind, monkeypatch):
    v = batch_victims[name]
    if v.task == "detection":  # keep every query, so the comparison has boxes to compare
        monkeypatch.setattr(v, "score_threshold", 0.0)
    x, ts = _images(3, seed=2).requires_grad_(True), _targets(v)
    calls = []
    hook = v.module.register_forward_hook(lambda *_: calls.append(1))
    try:
        per, preds = v.loss_and_predict(x, ts, kind)
    finally:
        hook.remove()
    assert len(calls) == 1
    assert per.shape == (3,) and per.requires_grad
    assert torch.allclose(per, v.losses(x, ts, kind), rtol=1e-6, atol=1e-7)
    _same_predictions(preds, v.predict(x))
    if v.task == "detection":
        assert all(len(p.scores) > 0 for p in preds)


def test_loss_and_predict_checks_like_loss(victims):
    with pytest.raises(VictimError, match=r"'vanish'.*does classification"):
        victims["torch_classifier"].loss_and_predict(_images(), Target(0), "vanish")
    with pytest.raises(VictimError, match="needs Target.box"):
        victims["torch_detector"].loss_and_predict(_images(), Target(0), "box")
    with pytest.raises(VictimError, match="one per image"):
        victims["torch_detector"].losses(_images(2), [Target(0)], "vanish")


# --------------------------------------------------------------------------- predict

def test_classifier_predict(victims):
    for name in ("torch_classifier", "hf_classifier"):
        preds = victims[name].predict(_images(3))
        assert len(preds) == 3
        for p in preds:
            assert 0 <= p.label < 3 and p.probs.shape == (3,)
            assert float(p.probs.sum()) == pytest.approx(1.0, abs=1e-5)
            assert p.label == int(p.probs.argmax())
            assert set(p.to_dict(LABELS)) == {"label", "score", "name"}


@pytest.mark.parametrize("name", ["torch_detector", "hf_detr", "hf_conditional_detr"])
def test_detector_predict_boxes_in_input_pixels(victims, name):
    v = victims[name]
    x = _images(2)
    preds = v.predict(x, threshold=0.0)
    raw = v.forward_raw(x)
    q = raw.boxes.shape[1]
    for i, p in enumerate(preds):
        assert p.boxes.shape == (q, 4) and p.scores.shape == (q,) and p.labels.shape == (q,)
        assert torch.all(p.scores[:-1] >= p.scores[1:])
        expect = losses.cxcywh_to_xyxy(raw.boxes[i]) * torch.tensor([W, H, W, H])
        # every predicted box is one of the raw boxes, scaled to the input's pixels
        d = (p.boxes[:, None, :] - expect[None]).abs().amax(-1).amin(1)
        assert d.max() < 1e-4
    high = v.predict(x, threshold=0.999)
    assert all(bool((p.scores >= 0.999).all()) for p in high)


def test_hf_labels_and_preprocess_read_from_folder(victims):
    cls, det = victims["hf_classifier"], victims["hf_detr"]
    assert cls.labels == LABELS and det.labels == LABELS
    assert cls.preprocess_config.crop == (32, 32)
    assert cls.preprocess_config.shortest_edge == int(32 / 0.875)
    assert det.preprocess_config.shortest_edge == 48 and det.preprocess_config.longest_edge == 64
    assert victims["hf_detr"].activation == "auto"
    assert victims["hf_conditional_detr"].forward_raw(_images(1)).activation == "sigmoid"
    assert victims["hf_detr"].forward_raw(_images(1)).activation == "softmax"


# --------------------------------------------------------------------------- preprocess

def test_detr_resize_rule():
    cfg = PreprocessConfig(shortest_edge=800, longest_edge=1333)
    assert cfg.resized_size(480, 640) == (800, 1066)
    assert cfg.resized_size(400, 1000) == (533, 1333)  # the long side caps it
    assert cfg.resized_size(640, 480) == (1066, 800)


def test_from_hf_variants():
    assert PreprocessConfig.from_hf({"size": {"height": 224, "width": 200}}).size == (224, 200)
    c = PreprocessConfig.from_hf({"size": {"shortest_edge": 224}, "crop_pct": 0.875})
    assert (c.shortest_edge, c.crop) == (256, (224, 224))
    c = PreprocessConfig.from_hf({"size": {"shortest_edge": 384}, "crop_pct": 0.875})
    assert (c.size, c.crop) == ((384, 384), None)
    c = PreprocessConfig.from_hf({"size": 800, "max_size": 1333})
    assert (c.shortest_edge, c.longest_edge) == (800, 1333)
    c = PreprocessConfig.from_hf({"size": 256, "do_center_crop": True, "crop_size": 224,
                                  "image_mean": [0.1, 0.2, 0.3], "image_std": [1, 2, 3]})
    assert (c.size, c.crop, c.mean, c.std) == ((256, 256), (224, 224), (0.1, 0.2, 0.3), (1, 2, 3))
    assert PreprocessConfig.from_hf({"size": 32, "do_resize": False}).size is None
    with pytest.raises(VictimError, match="preprocess.size"):
        PreprocessConfig.from_hf({"size": {"weird": 3}})


def test_preprocess_known_answer_and_shape():
    cfg = PreprocessConfig(size=(20, 30), crop=(10, 10), mean=(0.5, 0.5, 0.5), std=(0.5, 0.25, 1.0))
    x = torch.full((2, 3, 40, 60), 0.75)
    y = preprocess_images(x, cfg)
    assert y.shape == (2, 3, 10, 10)
    assert torch.allclose(y[:, 0], torch.tensor(0.5)) and torch.allclose(y[:, 1], torch.tensor(1.0))
    assert torch.allclose(y[:, 2], torch.tensor(0.25))
    assert preprocess_images(x, PreprocessConfig()).equal(x)


def test_preprocess_gradcheck():
    cfg = PreprocessConfig(size=(5, 7), crop=(4, 4), mean=(0.1, 0.2, 0.3), std=(0.5, 0.5, 0.5))
    x = torch.rand(1, 3, 9, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: preprocess_images(t, cfg), (x,))


def test_preprocess_config_errors():
    with pytest.raises(VictimError, match=r"preprocess.std: must be 3 numbers > 0"):
        PreprocessConfig(std=(1.0, 0.0, 1.0))
    with pytest.raises(VictimError, match="cannot be combined"):
        PreprocessConfig(size=(2, 2), shortest_edge=3)
    with pytest.raises(VictimError, match=r"crop: \(50, 50\) is larger"):
        preprocess_images(torch.rand(1, 3, 20, 20), PreprocessConfig(crop=(50, 50)))
    with pytest.raises(VictimError, match="must not crop"):
        Detector(TinyNet(3, 4), LABELS, PreprocessConfig(crop=(8, 8)))


# --------------------------------------------------------------------------- losses

def test_dlr_known_answer():
    z = torch.tensor([[3.0, 1.0, 0.0, -1.0]])
    assert float(losses.dlr(z, 0)) == pytest.approx(-(3 - 1) / (3 - 0))
    assert float(losses.dlr(z, 2)) == pytest.approx(-(0 - 3) / (3 - 0))
    # invariant to shift and positive scale
    assert float(losses.dlr(2 * z + 5, 2)) == pytest.approx(1.0)
    with pytest.raises(VictimError, match="at least 3 classes"):
        losses.dlr(torch.zeros(1, 2), 0)


def test_margin_is_clipped_so_frames_already_wrong_give_no_gradient():
    z = torch.tensor([[3.0, 1.0, 0.0], [0.0, 2.0, 1.0], [0.0, 9.0, 1.0]], requires_grad=True)
    per_image = losses.margin(z, 0, kappa=5.0, reduction="none")
    assert per_image.tolist() == [-2.0, 2.0, 5.0]  # right (< 0), wrong (> 0), wrong beyond kappa
    per_image.sum().backward()
    assert z.grad[0].tolist() == [-1.0, 1.0, 0.0]  # pushes the true logit down, the runner-up up
    assert z.grad[2].tolist() == [0.0, 0.0, 0.0]  # already wrong by kappa: nothing left to gain
    with pytest.raises(VictimError, match=r"class ids must be in \[0, 2\]"):
        losses.margin(z, 3)
    # why: ce's gradient fades on a frame the model is sure of and stays on one it already gets wrong
    zc = torch.tensor([[12.0, 0.0, 0.0], [0.0, 9.0, 1.0]], requires_grad=True)
    losses.ce_untargeted(zc, 0, reduction="none").sum().backward()
    assert float(zc.grad[0].norm()) < 1e-4 < 1.0 < float(zc.grad[1].norm())


def test_ce_losses_match_torch_and_sign():
    z = torch.tensor([[2.0, 0.5, -1.0], [0.0, 1.0, 0.0]])
    y = torch.tensor([0, 1])
    assert torch.allclose(losses.ce_untargeted(z, y), F.cross_entropy(z, y))
    assert torch.allclose(losses.ce_targeted(z, 2), -F.cross_entropy(z, torch.tensor([2, 2])))
    with pytest.raises(VictimError, match=r"class ids must be in \[0, 2\], got \[0, 5\]"):
        losses.ce_untargeted(z, torch.tensor([0, 5]))


def test_detection_losses_known_answers():
    # one image, two queries, two classes + no-object
    logits = torch.log(torch.tensor([[[0.6, 0.1, 0.3], [0.2, 0.2, 0.6]]]))
    lp = losses.class_log_probs(logits, "softmax")
    assert torch.allclose(lp.exp(), torch.tensor([[[0.6, 0.1], [0.2, 0.2]]]))
    boxes = torch.tensor([[[0.1, 0.1, 0.5, 0.5], [0.6, 0.6, 0.9, 0.9]]])
    true = torch.tensor([[0.1, 0.1, 0.5, 0.5]])
    w = losses.match_weights(lp, boxes, 0, true)
    assert torch.allclose(w, torch.tensor([[1.0, 0.0]]))  # only the overlapping query
    w_prob = losses.match_weights(lp, boxes, 0)  # no box: by true-class probability
    assert torch.allclose(w_prob, torch.tensor([[0.75, 0.25]]))
    assert float(losses.det_vanish(lp, 0, w)) == pytest.approx(-0.6)
    assert float(losses.det_vanish(lp, 0, w_prob)) == pytest.approx(-(0.75 * 0.6 + 0.25 * 0.2))
    assert float(losses.det_vanish(lp, 0, w_prob, reduce="max")) == pytest.approx(-0.6)
    assert float(losses.det_mislabel(lp, 1, w)) == pytest.approx(torch.log(torch.tensor(0.1)).item())
    assert float(losses.det_box(boxes, true, w)) == pytest.approx(0.0, abs=1e-6)
    far = torch.tensor([[[0.6, 0.1, 1.0, 0.5], [0.6, 0.6, 0.9, 0.9]]])
    # disjoint, same size: L1 = mean(|0.5|, 0, |0.5|, 0) = 0.25; GIoU = 0 - (0.36 - 0.32)/0.36
    assert float(losses.det_box(far, true, w)) == pytest.approx(0.25 + 1 + 0.04 / 0.36)


def _loss_calls() -> dict:
    """Each loss function with arguments for a batch of 3 images."""
    g = torch.Generator().manual_seed(3)
    z = torch.randn(3, 4, generator=g)
    y, t = torch.tensor([0, 1, 2]), torch.tensor([3, 0, 1])
    lp = losses.class_log_probs(torch.randn(3, 5, 3, generator=g), "softmax")
    boxes = losses.cxcywh_to_xyxy(0.25 + 0.5 * torch.rand(3, 5, 4, generator=g))
    true = torch.tensor([[0.1, 0.1, 0.5, 0.5], [0.2, 0.3, 0.9, 0.8], [0.0, 0.0, 0.4, 0.9]])
    w = losses.match_weights(lp, boxes, 0, true)
    return {"ce_untargeted": (losses.ce_untargeted, (z, y)),
            "ce_targeted": (losses.ce_targeted, (z, t)),
            "dlr": (losses.dlr, (z, y)),
            "det_vanish": (losses.det_vanish, (lp, 0, w)),
            "det_vanish_max": (losses.det_vanish, (lp, 0, w, "max")),
            "det_mislabel": (losses.det_mislabel, (lp, 1, w)),
            "det_box": (losses.det_box, (boxes, true, w))}


@pytest.mark.parametrize("name", list(_loss_calls()))
def test_loss_reductions_agree(name):
    fn, args = _loss_calls()[name]
    per = fn(*args, reduction="none")
    assert per.shape == (3,)
    assert torch.allclose(per.mean(), fn(*args), rtol=1e-6)
    assert torch.equal(fn(*args), fn(*args, reduction="mean"))
    with pytest.raises(VictimError, match=rf"{fn.__name__}\.reduction: must be one of mean, none, "
                                          r"got 'sum'"):
        fn(*args, reduction="sum")


def test_iou_giou_known_answer():
    a = torch.tensor([0.0, 0.0, 2.0, 2.0])
    b = torch.tensor([1.0, 1.0, 3.0, 3.0])
    iou, giou = losses.box_iou_giou(a, b)
    assert float(iou) == pytest.approx(1 / 7)
    assert float(giou) == pytest.approx(1 / 7 - (9 - 7) / 9)


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("images,pattern", [
    ([[0.5]], "must be a torch.Tensor"),
    (torch.zeros(1, 3, 4, 4, dtype=torch.uint8), r"float tensor .* got dtype torch.uint8"),
    (torch.zeros(3, 4, 4), r"shape B×3×H×W .* got \(3, 4, 4\)"),
    (torch.zeros(1, 4, 4, 4), r"got \(1, 4, 4, 4\)"),
    (torch.zeros(1, 3, 0, 4), r"got \(1, 3, 0, 4\)"),
    (torch.full((1, 3, 4, 4), float("nan")), "must be finite, got 48 NaN"),
    (torch.full((1, 3, 4, 4), 255.0), r"range \[255, 255\] \(0-255 values"),
    (torch.full((1, 3, 4, 4), -0.01), r"range \[-0.01, -0.01\]"),
])
def test_bad_images(images, pattern):
    with pytest.raises(VictimError, match=pattern):
        check_images(images)


def test_range_slack_allowed(victims):
    x = _images(1).clamp(0, 1)
    x[0, 0, 0, 0] = 1.00005
    victims["torch_classifier"].predict(x)


def test_bad_images_through_victim(victims):
    with pytest.raises(VictimError, match="images: values must be sRGB"):
        victims["hf_detr"].loss(_images() * 255, Target(0), "vanish")
    with pytest.raises(VictimError, match=r"images: must have shape"):
        victims["hf_classifier"].predict(torch.rand(3, H, W))


def test_wrong_loss_kind_names_task(victims):
    with pytest.raises(VictimError, match=r"'vanish'.*does classification.*ce, targeted_ce, dlr"):
        victims["hf_classifier"].loss(_images(), Target(0), "vanish")
    with pytest.raises(VictimError, match=r"'dlr'.*does detection"):
        victims["hf_detr"].loss(_images(), Target(0), "dlr")


def test_missing_target_fields(victims):
    with pytest.raises(VictimError, match="needs Target.target_label"):
        victims["hf_classifier"].loss(_images(), Target(0), "targeted_ce")
    with pytest.raises(VictimError, match="needs Target.box"):
        victims["hf_detr"].loss(_images(), Target(0), "box")
    with pytest.raises(VictimError, match=r"target.label: 7 is not a class"):
        victims["hf_detr"].loss(_images(), Target(7), "vanish")


def test_bad_target():
    with pytest.raises(VictimError, match="target.label"):
        Target(-1)
    with pytest.raises(VictimError, match=r"x1 > x0 and y1 > y0, got \(5.0, 5.0, 1.0, 9.0\)"):
        Target(0, box=(5.0, 5.0, 1.0, 9.0))
    with pytest.raises(VictimError, match="4 finite numbers"):
        Target(0, box=(1, 2, 3))


def test_unknown_model_id_offline(monkeypatch):
    from undream.settings import load_local

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # for huggingface_hub itself, which reads it too
    offline = load_local({"HF_HUB_OFFLINE": "1"}).hf_offline
    assert offline and load_local({"TRANSFORMERS_OFFLINE": "yes"}).hf_offline and not load_local({}).hf_offline
    with pytest.raises(VictimError, match=r"cannot load victim 'undream-tests/no-such-model'.*"
                                          r"not in the Hugging Face cache \(no network allowed here\).*save_pretrained"):
        load_victim("undream-tests/no-such-model", offline=offline)


def test_missing_folder(tmp_path):
    with pytest.raises(VictimError, match="no such folder"):
        load_victim(str(tmp_path / "nope"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(VictimError, match="not a complete save_pretrained checkpoint"):
        load_victim(str(tmp_path / "empty"))


def test_wrong_task(hf_paths):
    from undream.victims import HFClassifier, HFDetector
    with pytest.raises(VictimError, match=r"model type 'resnet' .* cannot do detection; "
                                          r"it does classification"):
        load_victim(hf_paths["classifier"], task="detection")
    with pytest.raises(VictimError, match=r"cls'.*cannot do detection"):
        HFDetector.from_pretrained(hf_paths["classifier"])
    with pytest.raises(VictimError, match=r"model type 'detr' .* cannot do classification"):
        HFClassifier.from_pretrained(hf_paths["detr"])
    with pytest.raises(VictimError, match="task: must be one of"):
        load_victim(hf_paths["detr"], task="segmentation")


def test_bad_model_output():
    v = Classifier(TinyNet(5), LABELS)  # five logits, three labels
    with pytest.raises(VictimError, match=r"logits of shape \(2, 3\).*got \(2, 5\)"):
        v.predict(_images())
    d = Detector(TinyNet(5, queries=4), LABELS)
    with pytest.raises(VictimError, match="logits have 6 classes per query.*expected 4.*or 3"):
        d.predict(_images())


def test_bundled_missing(monkeypatch, tmp_path):
    monkeypatch.setattr(registry, "BUNDLED_DIR", tmp_path)
    with pytest.raises(VictimError, match=r"bundled victim 'classifier': its weights are not present"):
        load_victim("bundled:classifier")
    with pytest.raises(VictimError, match=r"unknown; valid names are bundled:classifier"):
        load_victim("bundled:segmenter")


def test_bundled_present(monkeypatch, tmp_path, hf_paths):
    import shutil
    shutil.copytree(hf_paths["detr"], tmp_path / "detector")
    monkeypatch.setattr(registry, "BUNDLED_DIR", tmp_path)
    v = load_victim("bundled:detector")
    assert v.task == "detection" and v.labels == LABELS
    with pytest.raises(VictimError, match="does detection, cannot do classification"):
        load_victim("bundled:detector", task="classification")


def test_bad_device():
    with pytest.raises(VictimError, match="device: 'gpu0' is not a torch device"):
        Classifier(TinyNet(3), LABELS, device="gpu0")


def test_truncated_weights_are_one_victim_error(tmp_path):
    """A half-copied model.safetensors: a VictimError naming the folder, not safetensors' own exception."""
    import shutil

    from undream.victims import bundled_path

    folder = tmp_path / "trunc"
    shutil.copytree(bundled_path("classifier"), folder)
    weights = folder / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    with pytest.raises(VictimError, match=r"trunc.*not a complete save_pretrained checkpoint.*deserializ"):
        load_victim(str(folder), task="classification")


def test_undream_run_attacks_with_the_margin_loss(tmp_path):
    """Through `undream run`: `loss: margin` is accepted, every frame's loss stays at or under the
    clip, and the results name the loss."""
    scene = make_scene(tmp_path / "scene", n_frames=4, size=16)
    cfg = run_config(scene, make_victim(tmp_path / "victim"), name="margin", steps=3, holdout="none",
                     loss="margin", attack={"eps": 255.0})
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(write_yaml(tmp_path / "run.yaml", cfg)),
                          "--out", str(out), "--no-progress"], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    assert results["loss_kind"] == "margin"
    with open_store(None, out / "store") as store:
        jobs = [j for it in range(3) for j in store.jobs(results["run_id"], it)]
    assert len(jobs) == 12 and all(j.finite and j.loss <= losses.MARGIN_KAPPA for j in jobs)
