"""A small anchor-free one-stage detector in the shape of YOLOv8, in plain torch.

No torchvision and no ultralytics: convolutions, batch norm and SiLU only.

- backbone: a stride-2 stem and four stride-2 stages (a conv and residual
  blocks each), giving feature maps at strides 8, 16 and 32 (P3, P4, P5);
- neck: a top-down feature pyramid (1×1 laterals, nearest upsampling, a 3×3
  conv per level);
- head: decoupled per level, as YOLOv8's: a box branch giving the distances
  from the cell centre to the box's left, top, right and bottom sides
  (``softplus`` of the output, in units of the level's stride) and a class
  branch giving one logit per class (sigmoid scores, no "no object" class).

:meth:`YoloNet.forward` decodes every cell of every level into a candidate:
``B×N×(4 + C)``, the first four the box as xyxy in PIXELS OF THE MODEL INPUT,
the rest the class logits. ``N = sum over strides s of (h/s)·(w/s)``, levels in
order of stride, cells row-major (ultralytics' order). The input is the
preprocessed image (normalised RGB), ``B×3×h×w`` with h and w multiples of 32.

A model is saved as a folder: ``config.json`` (``model_type`` :data:`MODEL_TYPE`,
the architecture and the class names in Hugging Face's ``id2label`` form) and
``model.safetensors``; the training flow adds ``preprocessor_config.json``,
``training.json`` and ``MODEL_CARD.md`` as for the other bundled victims.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from undream.errors import VictimError

MODEL_TYPE = "undream_yolo"
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
STRIDES = (8, 16, 32)
PRIOR = 0.01  # initial class probability of every candidate (the class bias), as detectors start


@dataclass(frozen=True)
class YoloConfig:
    """The architecture: ``labels`` (class names, index = class id), ``widths``
    (channels of the stem and the four stages: strides 2, 4, 8, 16, 32),
    ``depth`` (residual blocks per stage), ``neck`` and ``head`` channels,
    ``input_size`` (the square model input the training used, pixels)."""

    labels: tuple[str, ...]
    widths: tuple[int, ...] = (16, 24, 32, 48, 64)
    depth: int = 1
    neck: int = 32
    head: int = 32
    input_size: int = 64
    strides: tuple[int, ...] = field(default=STRIDES)

    def __post_init__(self) -> None:
        if not self.labels or not all(isinstance(x, str) and x for x in self.labels):
            raise VictimError(f"yolo.labels: must be non-empty class names, got {self.labels!r}")
        if len(self.widths) != 5 or not all(isinstance(w, int) and w > 0 for w in self.widths):
            raise VictimError(f"yolo.widths: must be 5 positive channel counts, got {self.widths!r}")
        for name in ("depth", "neck", "head", "input_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise VictimError(f"yolo.{name}: must be a positive integer, got {v!r}")
        if tuple(self.strides) != STRIDES:
            raise VictimError(f"yolo.strides: must be {STRIDES}, got {self.strides!r}")
        if self.input_size % STRIDES[-1]:
            raise VictimError(f"yolo.input_size: must be a multiple of {STRIDES[-1]}, got {self.input_size}")

    def to_json(self) -> dict[str, Any]:
        """``config.json``'s content (Hugging Face's label keys beside the architecture)."""
        d = asdict(self)
        labels = d.pop("labels")
        return {"model_type": MODEL_TYPE, "architectures": ["UndreamYolo"],
                "num_labels": len(labels), "id2label": {str(i): n for i, n in enumerate(labels)},
                "label2id": {n: i for i, n in enumerate(labels)},
                **{k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}}

    @classmethod
    def from_json(cls, d: dict[str, Any], where: str = "config.json") -> "YoloConfig":
        if d.get("model_type") != MODEL_TYPE:
            raise VictimError(f"{where}: model_type {d.get('model_type')!r} is not an undream YOLO "
                              f"detector (expected {MODEL_TYPE!r})")
        try:
            id2label = {int(k): str(v) for k, v in d["id2label"].items()}
            labels = tuple(id2label[i] for i in range(len(id2label)))
            keys = ("widths", "depth", "neck", "head", "input_size", "strides")
            arch = {k: tuple(d[k]) if isinstance(d[k], list) else d[k] for k in keys if k in d}
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise VictimError(f"{where}: not a complete undream YOLO config ({type(err).__name__}: "
                              f"{err})") from None
        return cls(labels=labels, **arch)


def conv(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Sequential:
    """Conv (no bias), batch norm, SiLU: YOLOv8's ``Conv``."""
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False),
                         nn.BatchNorm2d(cout), nn.SiLU())


class Residual(nn.Module):
    """Two 3×3 convs with a skip connection (the bottleneck of YOLOv8's C2f)."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.body = nn.Sequential(conv(c, c), conv(c, c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class Head(nn.Module):
    """One level's decoupled head: ``B×4×h×w`` ltrb distances (strides, >= 0) and
    ``B×C×h×w`` class logits."""

    def __init__(self, cin: int, hidden: int, classes: int) -> None:
        super().__init__()
        self.box = nn.Sequential(conv(cin, hidden), conv(hidden, hidden), nn.Conv2d(hidden, 4, 1))
        self.cls = nn.Sequential(conv(cin, hidden), conv(hidden, hidden), nn.Conv2d(hidden, classes, 1))
        nn.init.constant_(self.cls[-1].bias, -math.log((1 - PRIOR) / PRIOR))
        nn.init.constant_(self.box[-1].bias, 0.5)  # softplus(0.5) ≈ 1 stride to each side

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return F.softplus(self.box(x)), self.cls(x)


def anchor_points(h: int, w: int, strides: Sequence[int] = STRIDES,
                  device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Every candidate's cell centre ``N×2`` (x, y pixels of an ``h×w`` model input)
    and its stride ``N``, in the candidates' order (levels by stride, cells row-major)."""
    points, steps = [], []
    for s in strides:
        ys, xs = torch.meshgrid(torch.arange(h // s, device=device), torch.arange(w // s, device=device),
                                indexing="ij")
        points.append(torch.stack(((xs.reshape(-1) + 0.5) * s, (ys.reshape(-1) + 0.5) * s), 1))
        steps.append(torch.full((points[-1].shape[0],), float(s), device=device))
    return torch.cat(points).float(), torch.cat(steps)


def ltrb_boxes(distances: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """xyxy boxes ``B×N×4`` from distances ``B×N×4`` (pixels) to the left, top, right and
    bottom sides of each point ``N×2`` (x, y pixels)."""
    return torch.cat((points[None] - distances[..., :2], points[None] + distances[..., 2:]), -1)


def decode_ltrb(ltrb: torch.Tensor, points: torch.Tensor, strides: torch.Tensor) -> torch.Tensor:
    """xyxy boxes ``B×N×4`` from distances ``B×N×4`` (in strides) to the sides of each point."""
    return ltrb_boxes(ltrb * strides[None, :, None], points)


class YoloNet(nn.Module):
    """The detector (see the module docstring). ``forward(x)``: ``B×3×h×w``
    preprocessed input → candidates ``B×N×(4 + C)`` (xyxy pixels, class logits)."""

    def __init__(self, config: YoloConfig) -> None:
        super().__init__()
        self.config = config
        w, n = config.widths, config.neck
        self.stem = conv(3, w[0], 3, 2)
        self.stages = nn.ModuleList(
            nn.Sequential(conv(w[i], w[i + 1], 3, 2), *(Residual(w[i + 1]) for _ in range(config.depth)))
            for i in range(4))
        self.lateral = nn.ModuleList(conv(w[i], n, 1) for i in (2, 3, 4))
        self.smooth = nn.ModuleList(conv(n, n) for _ in STRIDES)
        self.heads = nn.ModuleList(Head(n, config.head, len(config.labels)) for _ in STRIDES)

    @property
    def num_classes(self) -> int:
        return len(self.config.labels)

    def pyramid(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The neck's feature maps at strides 8, 16, 32."""
        feats, y = [], self.stem(x)
        for stage in self.stages:
            y = stage(y)
            feats.append(y)
        lat = [lay(f) for lay, f in zip(self.lateral, feats[1:])]  # strides 8, 16, 32
        out = [lat[2]]
        for f in (lat[1], lat[0]):  # top-down
            out.insert(0, f + F.interpolate(out[0], size=f.shape[-2:], mode="nearest"))
        return [sm(f) for sm, f in zip(self.smooth, out)]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        if h % STRIDES[-1] or w % STRIDES[-1]:
            raise VictimError(f"yolo: input height and width must be multiples of {STRIDES[-1]}, "
                              f"got {h}×{w}")
        ltrb, logits = [], []
        for head, f in zip(self.heads, self.pyramid(x)):
            d, c = head(f)
            ltrb.append(d.flatten(2).transpose(1, 2))
            logits.append(c.flatten(2).transpose(1, 2))
        points, strides = anchor_points(h, w, STRIDES, x.device)
        boxes = decode_ltrb(torch.cat(ltrb, 1), points, strides)
        return torch.cat((boxes, torch.cat(logits, 1)), -1)

    def save_pretrained(self, folder: str | Path) -> None:
        """Write ``config.json`` and ``model.safetensors`` into ``folder`` (made if needed)."""
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        (out / CONFIG_FILE).write_text(json.dumps(self.config.to_json(), indent=2) + "\n", encoding="utf-8")
        save_file({k: v.detach().contiguous() for k, v in self.state_dict().items()}, str(out / WEIGHTS_FILE))

    @classmethod
    def from_pretrained(cls, folder: str | Path) -> "YoloNet":
        """The model saved in ``folder`` by :meth:`save_pretrained`; a one-line
        :class:`VictimError` when the folder holds no undream YOLO detector."""
        path = Path(folder)
        model = cls(read_config(path))
        try:
            state = load_file(str(path / WEIGHTS_FILE))
        except (OSError, SafetensorError) as err:
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise VictimError(f"victim {str(folder)!r}: cannot read {WEIGHTS_FILE} ({first})") from None
        try:
            missing, unexpected = model.load_state_dict(state, strict=False)
        except RuntimeError as err:  # a tensor of the wrong shape
            raise VictimError(f"victim {str(folder)!r}: {WEIGHTS_FILE} does not fit its config.json "
                              f"({str(err).strip().splitlines()[-1].strip()})") from None
        if missing or unexpected:
            raise VictimError(f"victim {str(folder)!r}: {WEIGHTS_FILE} does not fit its config.json "
                              f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
        return model.eval()


def read_config(folder: Path) -> YoloConfig:
    """The :class:`YoloConfig` of a saved folder (one-line errors)."""
    path = folder / CONFIG_FILE
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise VictimError(f"victim {str(folder)!r}: cannot read {CONFIG_FILE} ({err})") from None
    if not isinstance(d, dict):
        raise VictimError(f"victim {str(folder)!r}: {CONFIG_FILE} is not a JSON object")
    return YoloConfig.from_json(d, str(path))


def is_yolo_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder whose ``config.json`` names :data:`MODEL_TYPE`."""
    p = Path(path) / CONFIG_FILE
    try:
        return p.is_file() and json.loads(p.read_text(encoding="utf-8")).get("model_type") == MODEL_TYPE
    except (OSError, ValueError, AttributeError):
        return False
