"""Loading YOLO-family victims: undream's own YOLO folders and ultralytics weights files.

- an undream YOLO folder (``config.json`` with ``model_type``
  :data:`undream.victims.yolo.MODEL_TYPE`, ``model.safetensors``, optionally
  ``preprocessor_config.json``): :func:`load_yolo_victim`;
- a YOLOv8/YOLO11 weights file (``*.pt``): :func:`load_ultralytics_victim`,
  through the ``ultralytics`` package when it can be imported. undream does
  not install it: it requires torchvision, which undream's tree leaves out
  (``deploy/setup.sh``). Without it the spec is refused in one line.

Every failure is one :class:`VictimError` line naming the spec.
"""
from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

import torch

from undream.errors import VictimError
from undream.victims.dense import DenseDetector
from undream.victims.preprocess import PreprocessConfig
from undream.victims.yolo import MODEL_TYPE, YoloNet, read_config

PROCESSOR_FILE = "preprocessor_config.json"  # Hugging Face's name, read as undream.victims.hf reads it
ULTRALYTICS_SUFFIXES = (".pt",)
ULTRALYTICS_MISSING = ("the ultralytics package is not installed, and undream does not install it (it "
                       "requires torchvision, which undream's tree leaves out); install ultralytics to "
                       "load YOLOv8/YOLO11 weights, or pass an undream YOLO folder")


def yolo_preprocess(folder: Path, input_size: int) -> PreprocessConfig:
    """The folder's ``preprocessor_config.json``, or a resize to ``input_size``² without normalisation."""
    path = folder / PROCESSOR_FILE
    if not path.is_file():
        return PreprocessConfig(size=(input_size, input_size))
    try:
        return PreprocessConfig.from_hf(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError) as err:
        raise VictimError(f"victim {str(folder)!r}: cannot read {PROCESSOR_FILE} ({err})") from None


def load_yolo_victim(spec: str | Path, device: str | torch.device = "cpu",
                     task: str | None = None) -> DenseDetector:
    """The undream YOLO detector saved in the folder ``spec`` as a victim."""
    folder = Path(spec).expanduser()
    if not folder.is_dir():
        raise VictimError(f"victim {str(spec)!r}: no such folder (expected an undream YOLO folder with "
                          f"config.json and model.safetensors)")
    if task not in (None, "detection"):
        raise VictimError(f"victim {str(spec)!r}: model type {MODEL_TYPE!r} does detection, cannot do {task}")
    config = read_config(folder)
    module = YoloNet.from_pretrained(folder)
    return DenseDetector(module, config.labels, yolo_preprocess(folder, config.input_size),
                         name=str(spec), device=device, strides=config.strides)


def _import_ultralytics(spec: str) -> Any:
    try:
        import ultralytics
    except ImportError:
        raise VictimError(f"victim {spec!r}: {ULTRALYTICS_MISSING}") from None
    return ultralytics


def load_ultralytics_victim(spec: str, device: str | torch.device = "cpu",
                            task: str | None = None) -> DenseDetector:
    """A YOLOv8/YOLO11 detection weights file (``*.pt``) as a victim, through
    ``ultralytics.YOLO``. The model input is the image resized (stretched, not
    letterboxed as ultralytics' own predictor does) to the square size it was
    trained at, sRGB in [0, 1] without normalisation, as ultralytics feeds it."""
    path = Path(spec).expanduser()
    if not path.is_file():
        raise VictimError(f"victim {spec!r}: no such file (expected YOLOv8/YOLO11 weights, *.pt)")
    if task not in (None, "detection"):
        raise VictimError(f"victim {spec!r}: an ultralytics weights file is loaded as a detector, "
                          f"cannot do {task}")
    ultralytics = _import_ultralytics(spec)
    try:
        yolo = ultralytics.YOLO(str(path))
    except (OSError, RuntimeError, ValueError, KeyError, TypeError, AttributeError, ImportError,
            pickle.UnpicklingError, EOFError) as err:  # what torch.load and ultralytics raise on a bad file
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise VictimError(f"victim {spec!r}: ultralytics cannot load it ({type(err).__name__}: {first})") from None
    if getattr(yolo, "task", None) != "detect":
        raise VictimError(f"victim {spec!r}: an ultralytics {getattr(yolo, 'task', None)!r} model, not a "
                          f"detector (task 'detect')")
    module = yolo.model.float()
    names = yolo.names
    labels = [str(names[i]) for i in range(len(names))]
    size = _square_size(getattr(module, "args", {}) or {})
    strides = tuple(int(s) for s in getattr(module, "stride", torch.tensor([8, 16, 32])).tolist())
    return DenseDetector(module, labels, PreprocessConfig(size=(size, size)), name=spec, device=device,
                         output_format="ultralytics", strides=strides)


def _square_size(args: dict[str, Any]) -> int:
    size = args.get("imgsz", 640) if isinstance(args, dict) else 640
    size = size[0] if isinstance(size, (list, tuple)) else size
    return int(size) if isinstance(size, int) and size % 32 == 0 and size > 0 else 640
