"""One entry point for every victim: :func:`load_victim`.

A spec is one of

- ``bundled:<name>``: the small models shipped in
  ``undream/victims/bundled/<name>/`` (a ``save_pretrained`` folder),
  trained on undream's own renders so that everything runs offline:
  ``classifier`` / ``detector`` (the first ones, trained on the ``v1`` data;
  also named ``classifier-v1`` / ``detector-v1``) and ``classifier-v2`` /
  ``detector-v2`` (trained on the ``v2`` data: camera heights 0.2–3.5 m,
  distances 1.5–8 m, every background and weather) and ``classifier-v3`` /
  ``detector-v3`` (the ``v3`` data: ``v2``'s, with plain, unsaturated objects too) and
  ``classifier-v4`` (the ``v3`` data twice over: 16,000 renders in two parts; no v4 detector);
- ``bundled:yolo``: undream's YOLO-style one-stage detector
  (:mod:`undream.victims.yolo`), trained from scratch on the ``v1`` data
  (``undream victims train --task detection --arch yolo``; model card in its folder);
- the path of an undream YOLO folder (``config.json`` with ``model_type``
  ``undream_yolo``: :mod:`undream.victims.yolo_load`);
- the path of a YOLOv8/YOLO11 weights file (``*.pt``), loaded through
  ``ultralytics`` when it is installed (refused in one line otherwise);
- ``coco:<name>``: a real COCO detector no one here trained, read from its
  TF.js graph in the model cache (``coco:centernet``, ``coco:nanodet``; :mod:`undream.victims.coco`),
  fetched there by ``deploy/setup.sh``;
- ``hf:<id or path>`` or just ``<id or path>``: a Hugging Face hub id (found
  in the local cache, or over the network where allowed) or the path of a
  ``save_pretrained`` folder.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from undream.errors import VictimError
from undream.settings import LocalSettings
from undream.victims.base import TASKS, Victim
from undream.victims import yolo_load
from undream.victims.yolo import is_yolo_folder

BUNDLED_DIR = Path(__file__).resolve().parent / "bundled"
# Folder name -> task.
BUNDLED = {"classifier": "classification", "detector": "detection",
           "classifier-v2": "classification", "detector-v2": "detection",
           "classifier-v3": "classification", "detector-v3": "detection", "classifier-v4": "classification",
           "classifier-at": "classification", "yolo": "detection"}
# How to get a bundled victim whose folder is absent.
NOT_SHIPPED = {"yolo": "this installation lacks its folder: train one with `undream victims train --task "
                       "detection --arch yolo` and pass its folder"}
# Other names of bundled victims -> their folder name.
BUNDLED_ALIASES = {"classifier-v1": "classifier", "detector-v1": "detector"}


def bundled_names() -> list[str]:
    """Every name ``bundled:<name>`` accepts: the folders, then their aliases."""
    return [*BUNDLED, *BUNDLED_ALIASES]


def bundled_folder_name(name: str) -> str:
    """The folder name of the bundled victim ``name`` (an alias resolved); a
    :class:`VictimError` listing the valid names for an unknown one."""
    folder = BUNDLED_ALIASES.get(name, name)
    if folder not in BUNDLED:
        raise VictimError(f"bundled victim {name!r}: unknown; valid names are "
                          f"{', '.join('bundled:' + n for n in bundled_names())}")
    return folder


def bundled_path(name: str) -> Path:
    """The folder of the bundled victim ``name`` or alias (it may not exist)."""
    return BUNDLED_DIR / bundled_folder_name(name)


def _load_bundled(name: str, task: str | None, device: str | torch.device) -> Victim:
    path = bundled_path(name)
    if not path.is_dir():
        how = NOT_SHIPPED.get(name, "install a build of undream that ships them, or pass a Hugging "
                                    "Face id or save_pretrained folder instead")
        raise VictimError(f"bundled victim {name!r}: its weights are not present (expected the "
                          f"folder {path}); {how}")
    if not (path / "config.json").is_file():
        raise VictimError(f"bundled victim {name!r}: {path} has no config.json (expected a "
                          f"save_pretrained folder)")
    own = BUNDLED[bundled_folder_name(name)]
    if task is not None and task != own:
        raise VictimError(f"bundled victim {name!r}: does {own}, cannot do {task}")
    return _load_path(str(path), own, device, offline=True)


def check_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch device this torch build can use; else a :class:`VictimError` saying why."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise VictimError(f"device: {device!r} is not a torch device ({err}); e.g. 'cpu' or 'cuda:0'") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        build = "has no CUDA" if torch.version.cuda is None else "finds no CUDA device"
        raise VictimError(f"device: {device!r}, but this torch build ({torch.__version__}) {build}; use 'cpu'")
    if dev.type not in ("cpu", "cuda"):
        raise VictimError(f"device: {device!r} is not supported; use 'cpu' or 'cuda[:N]'")
    return dev


def load_victim(spec: str, device: str | torch.device = "cpu", task: str | None = None,
                offline: bool = False, cache_home: str | None = None) -> Victim:
    """Load the victim named by ``spec`` (see the module docstring) on ``device``.

    ``task`` (``classification`` or ``detection``), when given, must be one the
    model can do; by default the model's own task is used. ``offline``: never
    ask the Hugging Face hub (the edge passes ``HF_HUB_OFFLINE``). ``cache_home``:
    the cache root whose ``undream/models`` holds fetched foreign models (the
    edge passes ``LocalSettings.cache_home``; None: ``~/.cache``).
    """
    if not isinstance(spec, str) or not spec.strip():
        raise VictimError(f"victim: must be a hub id, a folder or bundled:<name>, got {spec!r}")
    if task is not None and task not in TASKS:
        raise VictimError(f"task: must be one of {', '.join(TASKS)}, got {task!r}")
    check_device(device)
    if spec.startswith("bundled:"):
        return _load_bundled(spec[len("bundled:"):], task, device)
    if spec.startswith("coco:"):
        from undream.victims.coco import load_coco_victim
        home = cache_home if cache_home is not None else LocalSettings().cache_home
        return load_coco_victim(spec[len("coco:"):], Path(home) / "undream", device, task)
    if spec.startswith("hf:"):
        from undream.victims.hf import load_hf_victim
        return load_hf_victim(spec[len("hf:"):], task, device, offline)
    return _load_path(spec, task, device, offline)


def _load_path(spec: str, task: str | None, device: str | torch.device, offline: bool) -> Victim:
    """A folder or file by its kind: an undream YOLO folder, ultralytics weights, else Hugging Face."""
    from undream.victims.hf import load_hf_victim

    path = os.path.expanduser(spec)
    if is_yolo_folder(path):
        return yolo_load.load_yolo_victim(spec, device, task)
    if spec.endswith(yolo_load.ULTRALYTICS_SUFFIXES):
        return yolo_load.load_ultralytics_victim(spec, device, task)
    if os.path.isfile(path):
        raise VictimError(f"victim {spec!r}: is a file; pass a save_pretrained or undream YOLO folder, "
                          f"a YOLOv8/YOLO11 weights file (*.pt), a Hugging Face hub id or bundled:NAME")
    return load_hf_victim(spec, task, device, offline)
