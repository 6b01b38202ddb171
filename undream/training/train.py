"""Training and evaluating the bundled victims on undream's own renders.

Both are Hugging Face ``transformers`` models, saved with ``save_pretrained``
so that bundled and user victims share one loading path
(:func:`undream.victims.load_victim`):

- classifier: ``ResNetForImageClassification``, a small ResNet
  (:data:`RESNET_ARCH`) trained from scratch;
- detector: ``DetrForObjectDetection`` (:data:`DETR_ARCH`) whose ResNet
  backbone starts from the trained classifier (as DETR starts from an
  ImageNet ResNet: DETR freezes the backbone's batch-norm statistics, its stem
  and first stage), trained with DETR's own loss (cross-entropy with a
  no-object class, L1 and GIoU box terms, auxiliary decoder losses). Every
  image holds one object, and the detector has ONE query: with several, all
  queries learned the same box at a hedged score (about 2/3, the symmetric
  optimum of the no-object weighting), and the duplicates sank AP@0.5 to
  0.18 after 40 epochs; DETR breaks that symmetry only after far longer
  training than a CPU allows.
- detector, ``arch="yolo"``: undream's plain-torch YOLOv8-shaped detector
  (:class:`undream.victims.yolo.YoloNet`, :data:`undream.training.yolo.YOLO_ARCH`), trained from
  scratch with its centre-sampling loss (:mod:`undream.training.yolo`) and
  saved in its own folder layout (``config.json`` + ``model.safetensors``),
  which :func:`undream.victims.load_victim` recognises.

Images are 64×64 sRGB renders; the model input is the image resized to
:data:`INPUT_SIZE` and normalised, by the same differentiable preprocessing
(:func:`undream.victims.preprocess.preprocess_images`) that the victim
adapters apply at attack time. The preprocessing is written as the folder's
``preprocessor_config.json``.

Training is seeded: the initial weights, the batch order and the
augmentations come from ``TrainConfig.seed`` (same seed, data, thread count
and library versions → same weights).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from undream.errors import DatasetError, VictimError
from undream.spec.io import check_new_folder, restored_on_failure
from undream.versions import versions
from undream.training.dataset import CLASSES, Dataset, load_dataset, load_datasets
from undream.training.yolo import build_yolo, yolo_loss
from undream.victims.registry import load_victim
from undream.training.evaluation import evaluate
from undream.victims.preprocess import PreprocessConfig, preprocess_images

INPUT_SIZE = 64  # model input width = height in pixels (the renders' own size)
MEAN = (0.485, 0.456, 0.406)  # the usual ImageNet statistics, kept for familiarity
STD = (0.229, 0.224, 0.225)
RESNET_ARCH: dict[str, Any] = {"embedding_size": 32, "hidden_sizes": [32, 64, 128, 256],
                               "depths": [1, 1, 1, 1], "layer_type": "basic"}
# One query: see the module docstring.
DETR_ARCH: dict[str, Any] = {"num_queries": 1, "d_model": 128, "encoder_layers": 1,
                             "decoder_layers": 2, "encoder_attention_heads": 4,
                             "decoder_attention_heads": 4, "encoder_ffn_dim": 256,
                             "decoder_ffn_dim": 256, "auxiliary_loss": True}
DEFAULTS: dict[str, dict[str, Any]] = {
    "classification": {"epochs": 30, "lr": 2e-3, "weight_decay": 5e-4, "batch_size": 64},
    "detection": {"epochs": 40, "lr": 4e-4, "weight_decay": 1e-4, "batch_size": 32},
}
YOLO_DEFAULTS: dict[str, Any] = {"epochs": 60, "lr": 2e-3, "weight_decay": 5e-4, "batch_size": 32}
ARCHS = {"classification": ("resnet",), "detection": ("detr", "yolo")}
BACKBONE_LR_FACTOR = 0.1  # detector backbone (from the classifier) learns 10x slower
TRAINING_FILE = "training.json"


@dataclass(frozen=True)
class TrainConfig:
    """How to train. ``None`` fields take the task's :data:`DEFAULTS`.

    backbone: for detection, a trained classifier folder whose ResNet starts
    the detector's backbone (recommended; without it the backbone starts
    random and DETR keeps its stem frozen).
    arch: the model, one of the task's :data:`ARCHS` (default its first:
    ``resnet`` or ``detr``); ``yolo`` trains :class:`undream.victims.yolo.YoloNet`
    with :data:`YOLO_DEFAULTS`.
    """

    task: str
    seed: int = 0
    epochs: int | None = None
    lr: float | None = None
    batch_size: int | None = None
    backbone: Path | None = None
    threads: int | None = None
    input_size: int = INPUT_SIZE
    arch: str | None = None

    def __post_init__(self) -> None:
        if self.task not in DEFAULTS:
            raise VictimError(f"train.task: must be one of {', '.join(DEFAULTS)}, got {self.task!r}")
        if self.arch is not None and self.arch not in ARCHS[self.task]:
            raise VictimError(f"train.arch: {self.task} trains {', '.join(ARCHS[self.task])}, "
                              f"got {self.arch!r}")
        if self.model == "yolo" and self.backbone is not None:
            raise VictimError("train.backbone: only the DETR detector starts from a classifier's "
                              "backbone; the yolo detector trains from scratch")

    @property
    def model(self) -> str:
        """The architecture trained: ``arch``, or the task's default."""
        return self.arch or ARCHS[self.task][0]

    @property
    def defaults(self) -> dict[str, Any]:
        """The defaults of this task and architecture (:data:`DEFAULTS`, :data:`YOLO_DEFAULTS`)."""
        return YOLO_DEFAULTS if self.model == "yolo" else DEFAULTS[self.task]

    def get(self, name: str) -> Any:
        value = getattr(self, name)
        return self.defaults[name] if value is None else value


def preprocess_config(size: int = INPUT_SIZE) -> PreprocessConfig:
    """Resize to ``size``×``size`` (bilinear) and normalise with :data:`MEAN`, :data:`STD`."""
    return PreprocessConfig(size=(size, size), mean=MEAN, std=STD)


def processor_json(task: str, size: int = INPUT_SIZE) -> dict[str, Any]:
    """The ``preprocessor_config.json`` of a bundled model (Hugging Face keys)."""
    d: dict[str, Any] = {
        "image_processor_type": "DetrImageProcessor" if task == "detection" else "ViTImageProcessor",
        "do_resize": True, "size": {"height": size, "width": size}, "resample": 2,
        "do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
        "image_mean": list(MEAN), "image_std": list(STD)}
    if task == "detection":
        d.update(do_pad=False, format="coco_detection")
    return d


# --------------------------------------------------------------------------- models

def _label_maps() -> dict[str, Any]:
    return {"num_labels": len(CLASSES), "id2label": dict(enumerate(CLASSES)),
            "label2id": {c: i for i, c in enumerate(CLASSES)}}


def build_classifier() -> torch.nn.Module:
    """A fresh ResNet classifier over :data:`CLASSES` (random weights)."""
    from transformers import ResNetConfig, ResNetForImageClassification
    return ResNetForImageClassification(ResNetConfig(**RESNET_ARCH, **_label_maps()))


def build_detector(backbone: Path | None = None) -> torch.nn.Module:
    """A fresh DETR over :data:`CLASSES`; its backbone copied from the classifier
    folder ``backbone`` when given (same :data:`RESNET_ARCH`)."""
    from transformers import DetrConfig, DetrForObjectDetection, ResNetConfig
    bb = ResNetConfig(**RESNET_ARCH, out_features=["stage4"])
    model = DetrForObjectDetection(DetrConfig(backbone_config=bb, **DETR_ARCH, **_label_maps()))
    if backbone is not None:
        _copy_backbone(Path(backbone), model)
    # DETR means to train all but the backbone's stem and first stage, but matches timm's
    # parameter names ("stage.1"), so a transformers ResNet would stay frozen whole: say it here.
    for name, p in model.model.backbone.model.named_parameters():  # type: ignore[union-attr]
        p.requires_grad_(not name.startswith(("embedder.", "encoder.stages.0.")))
    return model


def build_model(cfg: TrainConfig) -> torch.nn.Module:
    """A fresh model of ``cfg``'s task and architecture (random weights, or DETR's backbone from
    ``cfg.backbone``)."""
    if cfg.model == "yolo":
        return build_yolo(tuple(CLASSES), cfg.input_size)
    return build_classifier() if cfg.task == "classification" else build_detector(cfg.backbone)


def _copy_backbone(folder: Path, detr: torch.nn.Module) -> None:
    from transformers import ResNetForImageClassification
    try:
        cls = ResNetForImageClassification.from_pretrained(str(folder), local_files_only=True)
    except (OSError, ValueError) as err:
        raise VictimError(f"train.backbone: {folder} is not a saved ResNet classifier ({err})") from None
    src = {k[len("resnet."):]: v for k, v in cls.state_dict().items() if k.startswith("resnet.")}
    dst = detr.model.backbone.model  # type: ignore[union-attr]
    own = dst.state_dict()
    missing = [k for k in own if k not in src and not k.endswith("num_batches_tracked")]
    shape = [k for k in own if k in src and own[k].shape != src[k].shape]
    if missing or shape:
        raise VictimError(f"train.backbone: {folder} does not fit the detector's backbone "
                          f"(missing {missing[:3]}, wrong shape {shape[:3]})")
    dst.load_state_dict({k: src[k] for k in own if k in src}, strict=False)


# --------------------------------------------------------------------------- augmentation

def augment(images: torch.Tensor, boxes: torch.Tensor, gen: torch.Generator,
            max_shift: int = 6) -> tuple[torch.Tensor, torch.Tensor]:
    """Random flip, shift, colour jitter and noise of ``B×3×H×W`` sRGB [0, 1] images.

    ``boxes`` ``B×4`` xyxy pixels follow the flip and the shift (clipped to
    the image). Returns new tensors.
    """
    b, _, h, w = images.shape
    x, bx = images.clone(), boxes.clone()
    flip = torch.rand(b, generator=gen) < 0.5
    x[flip] = x[flip].flip(-1)
    bx[flip] = torch.stack([w - boxes[flip, 2], boxes[flip, 1], w - boxes[flip, 0], boxes[flip, 3]], 1)
    pad = torch.nn.functional.pad(x, (max_shift,) * 4, mode="replicate")
    dx = torch.randint(-max_shift, max_shift + 1, (b,), generator=gen)
    dy = torch.randint(-max_shift, max_shift + 1, (b,), generator=gen)
    for i in range(b):  # the content moves by (dx, dy)
        x[i] = pad[i, :, max_shift - dy[i]:max_shift - dy[i] + h, max_shift - dx[i]:max_shift - dx[i] + w]
    bx += torch.stack([dx, dy, dx, dy], 1).to(bx.dtype)
    bx[:, 0::2] = bx[:, 0::2].clamp(0, w)
    bx[:, 1::2] = bx[:, 1::2].clamp(0, h)
    gain = 0.7 + 0.6 * torch.rand(b, 1, 1, 1, generator=gen)
    grey = x.mean(1, keepdim=True)
    sat = 0.6 + 0.8 * torch.rand(b, 1, 1, 1, generator=gen)
    x = (grey + sat * (x - grey)) * gain
    mean = x.mean((1, 2, 3), keepdim=True)
    x = mean + (0.75 + 0.5 * torch.rand(b, 1, 1, 1, generator=gen)) * (x - mean)
    x = x + 0.03 * torch.rand(b, 1, 1, 1, generator=gen) * torch.randn(x.shape, generator=gen)
    return x.clamp(0, 1), bx


def _tensors(ds: Dataset) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    images = torch.from_numpy(ds.images).permute(0, 3, 1, 2).contiguous()  # uint8 B×3×H×W
    return images, torch.from_numpy(ds.labels), torch.from_numpy(ds.boxes)


def _detr_targets(labels: torch.Tensor, boxes: torch.Tensor, h: int, w: int) -> list[dict[str, Any]]:
    """DETR labels: one object per image, boxes normalised cxcywh."""
    scale = torch.tensor([w, h, w, h], dtype=torch.float32)
    xyxy = boxes / scale
    cxcywh = torch.stack([(xyxy[:, 0] + xyxy[:, 2]) / 2, (xyxy[:, 1] + xyxy[:, 3]) / 2,
                          xyxy[:, 2] - xyxy[:, 0], xyxy[:, 3] - xyxy[:, 1]], 1)
    return [{"class_labels": lab[None], "boxes": box[None]} for lab, box in zip(labels, cxcywh)]


# --------------------------------------------------------------------------- training

def _schedule(total: int, warmup: int) -> Callable[[int], float]:
    def f(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, total - warmup)))
    return f


def optimiser_step(model: torch.nn.Module, opt: torch.optim.Optimizer, sched: Any, loss: torch.Tensor,
                   clip: float) -> float:
    """One update: the loss's gradient, clipped to norm ``clip``, an optimiser and a schedule step;
    returns the loss."""
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
    opt.step()
    sched.step()
    return float(loss.detach())


def fit(model: torch.nn.Module, ds: Dataset, cfg: TrainConfig, log: Callable[[str], None]) -> float:
    """Train ``model`` in place on ``ds``; returns the seconds spent."""
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    images, labels, boxes = _tensors(ds)
    n, (h, w) = len(labels), images.shape[-2:]
    bs, epochs = cfg.get("batch_size"), cfg.get("epochs")
    lr, wd = cfg.get("lr"), cfg.defaults["weight_decay"]
    detection, yolo = cfg.task == "detection", cfg.model == "yolo"
    if detection and not yolo:
        backbone = [p for name, p in model.named_parameters() if ".backbone." in name and p.requires_grad]
        rest = [p for name, p in model.named_parameters() if ".backbone." not in name and p.requires_grad]
        groups = [{"params": backbone, "lr": lr * BACKBONE_LR_FACTOR}, {"params": rest, "lr": lr}]
    else:
        groups = [{"params": [p for p in model.parameters() if p.requires_grad], "lr": lr}]
    opt = torch.optim.AdamW(groups, weight_decay=wd)
    steps = epochs * math.ceil(n / bs)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _schedule(steps, max(1, steps // 30)))
    pre = preprocess_config(cfg.input_size)
    start = time.perf_counter()
    model.train()
    for epoch in range(epochs):
        order = torch.randperm(n, generator=gen)
        total, seen = 0.0, 0
        for k in range(0, n, bs):
            idx = order[k:k + bs]
            x, bx = augment(images[idx].float() / 255.0, boxes[idx], gen)
            x = preprocess_images(x, pre)
            if yolo:
                scale = torch.tensor([cfg.input_size / w, cfg.input_size / h] * 2)
                loss, _ = yolo_loss(model(x), (bx * scale)[:, None], labels[idx][:, None], x.shape[-2:])
            elif detection:
                out = model(pixel_values=x, labels=_detr_targets(labels[idx], bx, h, w))
                loss = out.loss
            else:
                logits = model(pixel_values=x).logits
                loss = torch.nn.functional.cross_entropy(logits, labels[idx], label_smoothing=0.1)
            total += optimiser_step(model, opt, sched, loss, 0.1 if detection and not yolo else 5.0) * len(idx)
            seen += len(idx)
        log(f"epoch {epoch + 1}/{epochs}: loss {total / seen:.4f} "
            f"({time.perf_counter() - start:.0f} s)")
    model.eval()
    return time.perf_counter() - start


# --------------------------------------------------------------------------- the whole run

def train(data: str | Path | list[str | Path], test: str | Path, out: str | Path, cfg: TrainConfig,
          command: str = "", log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train on ``data`` (a dataset folder, or several parts of one set: :func:`.load_datasets`),
    save to ``out`` (``save_pretrained`` + preprocessor + ``training.json``), reload from disk as a
    victim and evaluate on ``test``. ``out`` must be new or empty (checked before training and
    again before saving); a failure leaves it as it was."""
    parts = [data] if isinstance(data, (str, Path)) else list(data)
    if Path(test).resolve() in {Path(p).resolve() for p in parts}:
        raise DatasetError(f"{test}: is both a training dataset and the held-out one; "
                           "a model judged on its own training images measures nothing")
    inputs = tuple(p for p in (*parts, test, cfg.backbone) if p is not None)
    check_new_folder(out, inputs=inputs)  # before minutes of training, not after
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    train_ds, test_ds = load_datasets(parts), load_dataset(test)
    log(f"{cfg.task}: {len(train_ds)} training images, {len(test_ds)} held-out images")
    torch.manual_seed(cfg.seed)
    model = build_model(cfg)
    seconds = fit(model, train_ds, cfg, log)
    out = Path(out)
    check_new_folder(out, inputs=inputs)  # still new after training (another command may have written it)
    with restored_on_failure(out):  # the folder goes back to how it was found
        return _save_and_evaluate(model, out, cfg, seconds, train_ds, test_ds, parts, test, command)


def _save_and_evaluate(model: Any, out: Path, cfg: TrainConfig, seconds: float, train_ds: Dataset,
                       test_ds: Dataset, parts: list[str | Path], test: str | Path,
                       command: str, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    model.save_pretrained(str(out))
    processor = processor_json(cfg.task, cfg.input_size)
    (out / "preprocessor_config.json").write_text(json.dumps(processor, indent=2) + "\n", encoding="utf-8")
    victim = load_victim(str(out), task=cfg.task)
    result = {"task": cfg.task, "command": command, "config": _jsonable(asdict(cfg)),
              "defaults": cfg.defaults, "train_seconds": round(seconds, 1),
              "threads": torch.get_num_threads(), "train_data": _about(train_ds, *parts),
              "test_data": _about(test_ds, test), "test": evaluate(victim, test_ds),
              "parameters": sum(p.numel() for p in model.parameters()),
              "versions": versions(), **(extra or {})}
    (out / TRAINING_FILE).write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    from undream.training.model_card import write_model_card
    write_model_card(out)
    return result


def _about(ds: Dataset, *folders: str | Path) -> dict[str, Any]:
    """A dataset's record in ``training.json``; a set of several parts (:func:`.load_datasets`) is
    recorded with its first part's config and every part's (``parts``)."""
    about = {"folder": ", ".join(str(f) for f in folders), "n": len(ds), "config": ds.metadata.get("config"),
             "mitsuba_variant": ds.metadata.get("mitsuba_variant"),
             "command": ds.metadata.get("command")}
    return {**about, "parts": ds.metadata["parts"]} if "parts" in ds.metadata else about


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}

