"""Hugging Face victims: image classifiers and DETR-style object detectors.

Loaded by hub id (from the local Hugging Face cache first; over the network
only when not ``offline``: the edge passes ``HF_HUB_OFFLINE``/``TRANSFORMERS_OFFLINE``,
:class:`undream.settings.LocalSettings`) or by the
path of a folder written by ``save_pretrained``. Preprocessing is read from
the folder's ``preprocessor_config.json`` and re-done in torch (see
:mod:`undream.victims.preprocess`). ``transformers`` is imported only when a
model is loaded.
"""
from __future__ import annotations

import json
import os
import warnings
from typing import Any, Callable

import torch

from undream.errors import VictimError
from undream.victims.base import Victim
from undream.victims.classifier import Classifier
from undream.victims.detector import Detector
from undream.victims.preprocess import PreprocessConfig

PROCESSOR_FILE = "preprocessor_config.json"


def _looks_like_path(spec: str) -> bool:
    """Hub ids are ``name`` or ``owner/name``; anything else is a path."""
    return (spec.startswith((".", "/", "~")) or spec.count("/") > 1
            or (os.sep != "/" and os.sep in spec) or os.path.exists(spec))


def _cannot_load(spec: str, err: BaseException | None = None, offline: bool = False) -> VictimError:
    why = f" ({type(err).__name__}: {str(err).splitlines()[0]})" if err else ""
    net = "no network allowed here" if offline else "not on the hub or no network"
    return VictimError(f"cannot load victim {spec!r}: not a local path and not in the Hugging Face "
                       f"cache ({net}); save it with save_pretrained and pass the folder{why}")


def _weights_errors() -> tuple[type[BaseException], ...]:
    """What safetensors raises on a truncated or corrupt weights file."""
    try:
        from safetensors import SafetensorError
    except ImportError:  # pragma: no cover - safetensors comes with transformers
        return ()
    return (SafetensorError,)


def _pretrained(load: Callable[..., Any], spec: str, offline: bool = False) -> tuple[Any, bool]:
    """``load(spec, local_files_only=...)``: the cache first, then the hub unless ``offline``.

    Returns the loaded object and whether it came from local files only.
    """
    if _looks_like_path(spec):
        path = os.path.expanduser(spec)
        if not os.path.isdir(path):
            raise VictimError(f"cannot load victim {spec!r}: no such folder (pass a folder written "
                              f"by save_pretrained, or a Hugging Face hub id)")
        try:
            return load(path, local_files_only=True), True
        except (OSError, ValueError, RuntimeError, *_weights_errors()) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise VictimError(f"cannot load victim {spec!r}: the folder is not a complete "
                              f"save_pretrained checkpoint ({first})") from None
    try:
        return load(spec, local_files_only=True), True
    except (OSError, ValueError) as err:
        if offline:
            raise _cannot_load(spec, offline=True) from err
    try:
        return load(spec, local_files_only=False), False
    except (OSError, ValueError) as err:
        raise _cannot_load(spec, err) from err


def load_hf_config(spec: str, offline: bool = False) -> tuple[Any, bool]:
    """The model's ``PretrainedConfig`` and whether it was found locally (the hub only unless ``offline``)."""
    from transformers import AutoConfig
    return _pretrained(AutoConfig.from_pretrained, spec, offline)


def hf_task(config: Any) -> str | None:
    """``classification``, ``detection`` or None for a transformers config."""
    from transformers.models.auto import modeling_auto as auto
    if type(config) in auto.MODEL_FOR_OBJECT_DETECTION_MAPPING:
        return "detection"
    if type(config) in auto.MODEL_FOR_IMAGE_CLASSIFICATION_MAPPING:
        return "classification"
    return None


def _check_task(spec: str, config: Any, task: str) -> None:
    found = hf_task(config)
    if found == task:
        return
    arch = ", ".join(getattr(config, "architectures", None) or []) or "unknown architecture"
    does = f"it does {found}" if found else \
        "it is neither an image classifier nor a DETR-style object detector"
    raise VictimError(f"victim {spec!r}: model type {config.model_type!r} ({arch}) cannot do "
                      f"{task}; {does}")


def load_hf_preprocess(spec: str, local_only: bool = True) -> PreprocessConfig | None:
    """The :class:`PreprocessConfig` from the model's ``preprocessor_config.json``,
    or None when it has none."""
    path = os.path.join(os.path.expanduser(spec), PROCESSOR_FILE)
    if not os.path.isdir(os.path.expanduser(spec)):
        from transformers.utils import cached_file
        path = cached_file(spec, PROCESSOR_FILE, local_files_only=local_only,
                           _raise_exceptions_for_missing_entries=False,
                           _raise_exceptions_for_connection_errors=False)
    if not path or not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            return PreprocessConfig.from_hf(json.load(fh))
    except (OSError, ValueError) as err:
        raise VictimError(f"victim {spec!r}: cannot read {PROCESSOR_FILE} ({err})") from err


def _labels(config: Any) -> list[str]:
    id2label = {int(k): str(v) for k, v in (getattr(config, "id2label", None) or {}).items()}
    n = int(getattr(config, "num_labels", len(id2label)))
    return [id2label.get(i, f"LABEL_{i}") for i in range(n)]


def _load(spec: str, task: str, preprocess: PreprocessConfig | None, offline: bool = False
          ) -> tuple[torch.nn.Module, list[str], PreprocessConfig]:
    import transformers
    config, local = load_hf_config(spec, offline)
    _check_task(spec, config, task)
    auto = (transformers.AutoModelForObjectDetection if task == "detection"
            else transformers.AutoModelForImageClassification)
    # transformers draws a "Loading weights" bar on stderr for every model: a victim loads
    # quietly, so that a run's error stays one line and its own bar the only one.
    transformers.utils.logging.disable_progress_bar()
    model, _ = _pretrained(auto.from_pretrained, spec, offline)
    if preprocess is None:
        preprocess = load_hf_preprocess(spec, local_only=local or offline)
        if preprocess is None:
            warnings.warn(f"victim {spec!r} has no {PROCESSOR_FILE}: images reach the model "
                          f"unresized and unnormalised", stacklevel=3)
            preprocess = PreprocessConfig()
    return model, _labels(config), preprocess


class HFClassifier(Classifier):
    """A Hugging Face ``AutoModelForImageClassification`` as a victim."""

    @classmethod
    def from_pretrained(cls, spec: str, device: str | torch.device = "cpu",
                        preprocess: PreprocessConfig | None = None, offline: bool = False) -> "HFClassifier":
        """Load by hub id or ``save_pretrained`` folder; ``preprocess`` overrides
        the model's ``preprocessor_config.json``; ``offline``: never ask the hub."""
        model, labels, pre = _load(spec, "classification", preprocess, offline)
        return cls(model, labels, pre, name=spec, device=device)


class HFDetector(Detector):
    """A Hugging Face DETR-style ``AutoModelForObjectDetection`` as a victim
    (DETR, YOLOS, Conditional/Deformable DETR, RT-DETR, ...: any model whose
    output has ``logits`` and normalised cxcywh ``pred_boxes``)."""

    @classmethod
    def from_pretrained(cls, spec: str, device: str | torch.device = "cpu",
                        preprocess: PreprocessConfig | None = None,
                        score_threshold: float = 0.5, offline: bool = False) -> "HFDetector":
        """Load by hub id or ``save_pretrained`` folder; see :class:`Detector`; ``offline``: never ask the hub."""
        model, labels, pre = _load(spec, "detection", preprocess, offline)
        return cls(model, labels, pre, name=spec, device=device, score_threshold=score_threshold)


def load_hf_victim(spec: str, task: str | None = None,
                   device: str | torch.device = "cpu", offline: bool = False) -> Victim:
    """A Hugging Face victim; the task is the model's own unless ``task`` is given; ``offline``:
    from local files only, never the hub."""
    if task is None:
        config, _ = load_hf_config(spec, offline)
        task = hf_task(config)
        if task is None:
            _check_task(spec, config, "classification or detection")
    if task == "classification":
        return HFClassifier.from_pretrained(spec, device=device, offline=offline)
    if task == "detection":
        return HFDetector.from_pretrained(spec, device=device, offline=offline)
    raise VictimError(f"task: must be classification or detection, got {task!r}")
