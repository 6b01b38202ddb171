"""Training records and model cards of trained victims, and the checks of the bundled ones.

Each folder is a Hugging Face ``save_pretrained`` checkpoint (``config.json``,
``model.safetensors``, ``preprocessor_config.json``) plus ``training.json``
(the run's config, data, timings and held-out numbers, written by
:func:`undream.training.train.train`) and ``MODEL_CARD.md`` (made from it by
:func:`model_card`). They load offline with
``undream.victims.load_victim("bundled:classifier")`` /
``("bundled:detector")``, through the same Hugging Face adapters as any user
model (see :mod:`undream.victims.registry`).
"""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from undream.errors import VictimError
from undream.training import distribution_v2 as v2
from undream.training import distribution_v3 as v3
from undream.training.bands import Bands
from undream.training.dataset import CLASSES, TRAINING_BACKGROUNDS, WEATHER_WEIGHTS, bands_of
from undream.training.textures import PLAIN_SATURATION, PLAIN_SHARE, PLAIN_VALUE
from undream.victims.registry import BUNDLED, bundled_folder_name, bundled_path
from undream.victims.yolo import MODEL_TYPE as YOLO_MODEL_TYPE

MAX_WEIGHTS_BYTES = 10 * 1024 * 1024
WEIGHTS_FILE = "model.safetensors"
CARD_FILE = "MODEL_CARD.md"
REPRODUCE = "scripts/make_bundled_victims.sh"


def weights_bytes(folder: str | Path) -> int:
    """Size of the folder's weights file in bytes."""
    path = Path(folder) / WEIGHTS_FILE
    if not path.is_file():
        raise VictimError(f"{folder}: has no {WEIGHTS_FILE}")
    return path.stat().st_size


def training_record(folder: str | Path) -> dict[str, Any]:
    """The ``training.json`` of a trained model folder."""
    path = Path(folder) / "training.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise VictimError(f"{path}: cannot read the training record ({err})") from None


def bundled_record(name: str) -> dict[str, Any]:
    """The training record of the bundled victim ``name`` (e.g. ``classifier``, ``detector-v2``)."""
    return training_record(bundled_path(name))


def _split_table(bands: Bands) -> str:
    rows = ["| parameter | range | band width | train bands | test bands |", "|---|---|---|---|---|"]
    for name, (lo, hi, width) in bands.items():
        edges = [lo + k * width for k in range(int(round((hi - lo) / width)) + 1)]
        bands = [f"[{a:g}, {b:g})" for a, b in zip(edges, edges[1:])]
        rows.append(f"| {name} | [{lo:g}, {hi:g}) | {width:g} | {' '.join(bands[0::2])} | "
                    f"{' '.join(bands[1::2])} |")
    return "\n".join(rows)


def _fmt(v: Any) -> str:
    return "n/a" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v)


GROUP_TITLES = {"weather": "weather", "background": "background", "height_m": "camera height (m)",
                "distance_m": "camera ground distance (m)", "elevation_deg": "camera elevation (°)",
                "coverage": "object size / frame width"}


def group_tables(test: dict[str, Any]) -> list[str]:
    """Markdown tables of an evaluation's ``per_group`` numbers (none if it has none)."""
    per = test.get("per_group", {})
    lines = ["", "Per group of held-out images (camera bands: the held-out bands):"] if per else []
    for grouping, groups in per.items():
        measure = next(k for k in next(iter(groups.values())) if k != "n")
        lines += ["", f"| {GROUP_TITLES.get(grouping, grouping)} | images | {_MEASURES[measure]} |",
                  "|---|---|---|"]
        lines += [f"| {name} | {g['n']} | {_fmt(g[measure])} |" for name, g in groups.items()]
    return lines


_MEASURES = {"accuracy": "accuracy", "ap50": "AP@0.5"}


def _data_text(distribution: str) -> str:
    """What the renders of a distribution show (the model card's Data paragraph, after its size)."""
    common = ("each with ONE built-in object at a random yaw, with a random texture (solid, stripes, "
              "checker, smooth noise or a mix, random colours) so that the model learns shape rather "
              "than a texture, ")
    if distribution == v3.NAME:
        common = (f"each with ONE built-in object at a random yaw, with a random texture: in {PLAIN_SHARE:.0%} "
                  "of the images a plain one (one colour of any hue, HSV saturation "
                  f"{PLAIN_SATURATION[0]:g}–{PLAIN_SATURATION[1]:g}, value {PLAIN_VALUE[0]:g}–{PLAIN_VALUE[1]:g} "
                  "in sRGB: grey, white, black or a muted tint, as an untextured object shows), else "
                  "solid, stripes, checker, smooth noise or a mix in random colours, so that the model "
                  "learns shape rather than a texture, ")
    if distribution in (v2.NAME, v3.NAME):
        return (common + "on a random background (" + ", ".join(v2.BACKGROUNDS) + "), under a random "
                "environment (weather " + ", ".join(f"{k} {v:.0%}" for k, v in v2.WEATHER_WEIGHTS_V2.items())
                + "; time of day across the day; sun height; fog density), seen by a camera placed like "
                f"one in a street (distribution `{distribution}`, `undream.training.distribution_{distribution}`"
                + ("" if distribution == v2.NAME else ", whose camera and environments are `v2`'s") + "): its height "
                "above the ground (0.2–3.5 m), its horizontal distance from the object (1.5–8 m), its "
                "azimuth about the object and its field of view (12–66°, redrawn with the distance until "
                f"the object's bounding sphere spans {v2.COVERAGE[0]:g}–{v2.COVERAGE[1]:g} of the frame "
                "width), looking at the object with a small off-centre shift. Boxes are the tight box of "
                "the object's visible pixels (the `mask` view).")
    return (common + "on a random background (plain, park with trees, street with buildings), under a "
            "random environment (weather " + ", ".join(f"{k} {v:.0%}" for k, v in WEATHER_WEIGHTS.items())
            + "; time of day; sun height; fog density), seen by a random camera (azimuth and "
            "elevation about the object, field of view, object size in the frame, off-centre "
            "look-at). Boxes are the tight box of the object's visible pixels (the `mask` view).")


def _split_text(distribution: str) -> str:
    if distribution in (v2.NAME, v3.NAME):
        return ("No held-out image shares a time of day, fog density, camera azimuth, height, ground "
                "distance or field of view with any training image. Every weather and background "
                "occurs in both; object yaw, sun height, look-at offset and textures are drawn the "
                "same way in both.")
    return ("No held-out image shares a time of day, fog density, camera azimuth, elevation, field of "
            "view or object size in the frame with any training image. Weather kinds, backgrounds "
            f"({', '.join(TRAINING_BACKGROUNDS)}) and texture kinds occur in both; object yaw, sun "
            "height, look-at offset and textures are drawn the same way in both.")


def _model_config(folder: Path) -> dict[str, Any]:
    path = folder / "config.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise VictimError(f"{path}: cannot read the model config ({err})") from None


def model_card(folder: str | Path, commands: list[str] | None = None, note: str = "") -> str:
    """The Markdown model card of a model folder, from its ``training.json`` (see
    :func:`write_model_card`)."""
    folder = Path(folder)
    rec = training_record(folder)
    task, test = rec["task"], rec["test"]
    size = weights_bytes(folder)
    tr, te = rec["train_data"], rec["test_data"]
    config = _model_config(folder)  # the architecture as saved, not as the code says today
    distribution = tr["config"].get("distribution", "v1")
    suffix = _suffix(folder, distribution)
    adversarial = rec.get("adversarial")
    if task == "classification":
        r = config
        title = f"bundled:classifier{suffix} — ResNet image classifier"
        arch = (f"`transformers` `ResNetForImageClassification` ({r['layer_type']} "
                f"blocks, depths {r['depths']}, widths {r['hidden_sizes']}, "
                f"stem {r['embedding_size']}), trained from scratch.")
        if adversarial:
            title = f"bundled:{folder.name} — adversarially trained ResNet image classifier"
            arch = arch.replace("trained from scratch.", f"`{adversarial['base']}` fine-tuned against attacked "
                                "textures (PGD-AT on the object's texture, below).")
        numbers = [f"- **accuracy: {_fmt(test['accuracy'])}** ({test['n_correct']}/{test['n_images']})",
                   "- per class: " + ", ".join(f"{k} {_fmt(v)}" for k, v in test["per_class"].items()),
                   "- per weather: " + ", ".join(f"{k} {_fmt(v)}" for k, v in test["per_weather"].items())]
    elif config.get("model_type") == YOLO_MODEL_TYPE:
        title, arch, numbers = _yolo_card(config, test)
    else:
        d = config
        title = f"bundled:detector{suffix} — DETR object detector"
        arch = ("`transformers` `DetrForObjectDetection`: the classifier's ResNet as backbone "
                "(stage 4, stride 32; frozen batch norm, stem and first stage, as DETR does), "
                f"d_model {d['d_model']}, {d['encoder_layers']} encoder and {d['decoder_layers']} "
                f"decoder layers, {d['encoder_attention_heads']} heads, FFN {d['encoder_ffn_dim']}, "
                f"{d['num_queries']} object quer{'y' if d['num_queries'] == 1 else 'ies'}, softmax "
                f"over the {len(CLASSES)} classes + no-object; trained with DETR's own loss "
                "(cross-entropy, L1 and GIoU box terms, auxiliary decoder losses). One query "
                "because every image holds one object: with six, all queries kept predicting the "
                "same box at a hedged score and the duplicates sank AP@0.5 to 0.18 after 40 "
                "epochs (see `undream/training/train.py`).")
        numbers = [f"- **AP@0.5: {_fmt(test['ap50'])}** (mean over the 6 classes of COCO AP at IoU 0.5, "
                   f"pycocotools; every query's best class and score, as COCO scores DETR)",
                   "- per class: " + ", ".join(f"{k} {_fmt(v)}" for k, v in test["ap50_per_class"].items()),
                   f"- AP@0.5 counting only detections scoring ≥ 0.5 (the victim's default "
                   f"threshold): {_fmt(test['ap50_thr05'])}",
                   f"- top detection has the right class and IoU ≥ 0.5: {_fmt(test['top1_correct'])} "
                   "(per weather: " + ", ".join(f"{k} {_fmt(v)}" for k, v in
                                               test["top1_per_weather"].items()) + ")"]
    cfg = rec["config"]
    px = cfg.get("input_size")
    cmds = commands or _commands(rec)
    lines = [
        f"# {title}", "",
        f"Classes (id: name): {', '.join(f'{i}: {c}' for i, c in enumerate(CLASSES))} — the "
        "built-in assets of `undream.scene.builtin`.", "",
        "## Data", "",
        "undream's own renders (`undream victims make-dataset`, module "
        f"`undream.training.dataset`): {tr['config']['size']}×{tr['config']['size']} sRGB images, "
        f"{tr['config']['spp']} spp, path traced by the project's scene adapter (`volpath` in "
        "fog, rain and snow), " + _data_text(distribution), "",
        f"- training set: {tr['n']} images ({_seeds(tr)}, split `train`)",
        f"- held-out set: {te['n']} images (seed {te['config']['seed']}, split `test`)",
        f"- rendered with Mitsuba variant `{tr.get('mitsuba_variant')}`", "",
        "Held-out split: train and test draw environments and camera poses from DISJOINT sets. "
        "Each parameter below is cut into equal bands that alternate between the splits, an "
        "odd number of them (azimuth is cyclic), so every held-out band lies between two "
        "training bands: the held-out set interpolates, it never extrapolates. "
        + _split_text(distribution), "",
        _split_table(bands_of(distribution)), "",
        "## Model", "",
        arch, "",
        f"- parameters: {rec['parameters']:,}",
        f"- weights: `{WEIGHTS_FILE}`, {size / 1e6:.2f} MB (float32)",
        f"- input: sRGB in [0, 1], resized to {px}×{px} (bilinear) and normalised with the "
        "ImageNet mean/std (`preprocessor_config.json`; undream redoes this differentiably).", "",
        "## Held-out results", "",
        *numbers, *group_tables(test), "",
        *(_adversarial_lines(adversarial) if adversarial else [
            "## Training", "",
            f"- seed {cfg['seed']}, {rec['defaults']['epochs'] if cfg['epochs'] is None else cfg['epochs']} "
            f"epochs, AdamW, cosine schedule, batch {rec['defaults']['batch_size']}; augmentation: "
            "horizontal flip, ±6 px shift, brightness/saturation/contrast jitter, pixel noise"]),
        f"- {rec['train_seconds'] / 60:.1f} min on {rec['threads']} CPU "
        f"thread{'' if rec['threads'] == 1 else 's'}; "
        f"torch {rec['versions']['torch']}, transformers {rec['versions']['transformers']}", "",
        "## Reproduce", "",
        f"`{REPRODUCE}` runs the whole pipeline with the seeds used here; this model came from:", "",
        "```", *cmds, "```", "",
        *([note, ""] if note else []),
        "## Limits", "",
        "- Only the six built-in assets, one object per image, 64-pixel renders of undream's "
        "own scenes: not a general-purpose model.",
        f"- Trained on square images; other aspect ratios are squashed to {px}×{px}.", ""]
    return "\n".join(lines)


def _adversarial_lines(adv: dict[str, Any]) -> list[str]:
    """The model card's account of adversarial training (:mod:`undream.training.adversarial`) and its
    held-out robust accuracy against the base model's."""
    c, before, after, fid = adv["config"], adv["held_out_base"], adv["held_out"], adv["composite_fidelity"]
    rows = ["| held-out images | " + f"`{adv['base']}` (base) | this model |", "|---|---|---|",
            f"| rendered, their own textures | {_fmt(before['clean'])} | {_fmt(after['clean'])} |",
            f"| composited, their own textures | {_fmt(before['composite'])} | {_fmt(after['composite'])} |"]
    for eps in before["robust"]:
        rows.append(f"| texture attacked, ε {eps} | {_fmt(before['robust'][eps])} | {_fmt(after['robust'][eps])} |")
    return [
        "## Robust accuracy (held-out)", "",
        f"Accuracy on the {after['n_images']} held-out images (their shading: `make-dataset --shading`), as rendered, "
        "and with the object's texture attacked by PGD on the composite (untargeted cross-entropy, a uniform "
        f"random start in the ε-ball of the image's own sRGB texture, {after['pgd_steps']} sign steps of 2.5 ε / "
        f"steps; seed {after['seed']}):", "", *rows, "",
        "This is the attack the training saw (white-box, on the composite). undream's own attack on the trained "
        "model (Mitsuba renders, the adaptive attack) is in docs/results.md, \"Defended victims\".", "",
        "## Training", "",
        f"- PGD-AT on the texture (the PBCAT idea): each batch of {c['batch_size']} is {c['clean_share']:.0%} rendered "
        f"images and the rest the composites of their textures attacked by PGD ({c['steps']} steps, random start; ε "
        f"drawn per image from {', '.join(str(e) for e in c['eps'])}, 0–255 sRGB) against the model as it is, then "
        "one AdamW step on all of them (cross-entropy, label smoothing 0.1; the base's augmentation)",
        f"- the composite: `black + (white − black) · lin(t)(uv)` per pixel from the image's shading (its "
        "radiance under a black and a white texture, the object's uv), the texture looked up as Mitsuba's "
        f"bitmap does; against the renders of the images' own textures: {fid['test']['psnr_db']} dB PSNR on "
        f"the held-out set (mean |difference| on the object's pixels {fid['test']['object_mean_abs_255']} of "
        f"255), {fid['train']['psnr_db']} dB on the training set",
        f"- seed {c['seed']}, {c['epochs']} epochs, lr {c['lr']:g}, cosine schedule"]


def _yolo_card(c: dict[str, Any], test: dict[str, Any]) -> tuple[str, str, list[str]]:
    """Title, architecture and held-out lines of an undream YOLO detector's card."""
    arch = ("undream's plain-torch YOLOv8-shaped detector (`undream.victims.yolo.YoloNet`): a "
            f"stride-2 stem and four stride-2 stages (widths {c['widths']}, {c['depth']} residual "
            f"block{'s' if c['depth'] != 1 else ''} each), a top-down feature pyramid at strides "
            f"{c['strides']} ({c['neck']} channels) and a decoupled head per level ({c['head']} "
            "channels: ltrb distances to the box's sides, one sigmoid score per class); trained from "
            "scratch with centre-sampling assignment, BCE on the class scores and 1 − GIoU on the "
            "boxes (`undream.training.yolo`).")
    numbers = [f"- **AP@0.5: {_fmt(test['ap50'])}** (mean over the 6 classes of COCO AP at IoU 0.5, "
               "pycocotools; every detection left by class-aware NMS at IoU 0.7, no score threshold)",
               "- per class: " + ", ".join(f"{k} {_fmt(v)}" for k, v in test["ap50_per_class"].items()),
               f"- AP@0.5 counting only detections scoring ≥ 0.5: {_fmt(test['ap50_thr05'])}",
               f"- top detection has the right class and IoU ≥ 0.5: {_fmt(test['top1_correct'])} "
               "(per weather: " + ", ".join(f"{k} {_fmt(v)}" for k, v in
                                           test["top1_per_weather"].items()) + ")"]
    return "bundled:yolo — YOLO-style one-stage detector", arch, numbers


def _suffix(folder: Path, distribution: str) -> str:
    """The bundled name's version: the folder's own where it is named as the bundled ones are
    (``classifier-v4``: a model of a later version trained on an earlier distribution's data),
    else the data's distribution (none for ``v1``)."""
    named = re.fullmatch(r"(classifier|detector)(-v\d+)", folder.name)
    if named:
        return named.group(2)
    return "" if distribution == "v1" else f"-{distribution}"


def _seeds(data: dict[str, Any]) -> str:
    """"seed 0", or "seeds 0 and 1 (2 parts of 8000)" for a set rendered in parts."""
    parts = data.get("parts")
    if not parts:
        return f"seed {data['config']['seed']}"
    seeds = [str(p["config"]["seed"]) for p in parts]
    sizes = sorted({p["n"] for p in parts})
    each = f"of {sizes[0]}" if len(sizes) == 1 else "of " + ", ".join(str(p["n"]) for p in parts)
    return f"seeds {', '.join(seeds[:-1])} and {seeds[-1]} ({len(parts)} parts {each})"


def _commands(rec: dict[str, Any]) -> list[str]:
    """The commands that made a model: its datasets, its backbone (if any), its training."""
    parts = rec["train_data"].get("parts") or [rec["train_data"]]
    cmds = [*(p.get("command") for p in parts), rec["test_data"].get("command")]
    backbone = rec["config"].get("backbone")
    if backbone and (Path(backbone) / "training.json").is_file():
        cmds.append(training_record(backbone).get("command"))
    cmds.append(rec.get("command"))
    return [c for c in cmds if c]


def write_model_card(folder: str | Path, commands: list[str] | None = None,
                     note: str = "") -> Path:
    """Write ``MODEL_CARD.md`` into ``folder`` from its ``training.json``; returns its path.

    ``commands`` replace the recorded ones (e.g. the same run with the
    folder names of :data:`REPRODUCE`); ``note`` follows them.
    """
    path = Path(folder) / CARD_FILE
    path.write_text(model_card(folder, commands, note), encoding="utf-8")
    return path


def check_bundled(name: str) -> dict[str, Any]:
    """Sizes and presence of the bundled victim ``name``'s files (raises when incomplete)."""
    folder = bundled_path(name)
    missing = [f for f in ("config.json", WEIGHTS_FILE, "preprocessor_config.json", CARD_FILE)
               if not (folder / f).is_file()]
    if missing:
        raise VictimError(f"bundled victim {name!r}: {folder} lacks {', '.join(missing)}")
    size = weights_bytes(folder)
    if size > MAX_WEIGHTS_BYTES:
        raise VictimError(f"bundled victim {name!r}: weights are {size} bytes, more than "
                          f"{MAX_WEIGHTS_BYTES}")
    return {"name": name, "task": BUNDLED[bundled_folder_name(name)], "folder": str(folder),
            "weights_bytes": size}
