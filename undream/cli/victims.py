"""``undream victims``: make the bundled victims' datasets, train and evaluate them.

Registered on ``undream`` by :mod:`undream.cli`; the work is in
:mod:`undream.training`. Heavy imports (Mitsuba, torch, transformers) happen
inside the commands. Errors are one line on stderr and exit status 2.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import click

from undream.cli.errors import one_line_errors
from undream.errors import VictimError
from undream.cli.options import local_settings, out_option, progress_option, seed_option, spp_option


def _command() -> str:
    """This command line as ``undream victims ...`` (for metadata and model cards)."""
    args = sys.argv[1:]
    if "victims" in args:
        args = args[args.index("victims") + 1:]
    return " ".join(["undream", "victims", *args])


@click.group("victims")
def victims() -> None:
    """Datasets, training and evaluation of the bundled victims."""


@victims.command("make-dataset")
@out_option("Folder to write (images/, labels.jsonl, metadata.json).")
@click.option("--n", "n", required=True, type=click.IntRange(1, 10**6), help="Number of images.")
@seed_option
@click.option("--split", default="train", show_default=True, type=click.Choice(["train", "test"]),
              help="Which disjoint set of environments and camera poses to draw from.")
@click.option("--size", default=64, show_default=True, type=click.IntRange(16, 1024),
              help="Image width and height in pixels.")
@spp_option("--spp", 16, "Samples per pixel.")
@click.option("--distribution", default="v1", show_default=True, type=click.Choice(["v1", "v2", "v3"]),
              help="v1: the orbiting camera of bundled:classifier/detector; v2: camera height "
                   "and ground distance, every background and weather (bundled:*-v2); v3: v2 with "
                   "plain, unsaturated objects too (bundled:*-v3).")
@click.option("--shading", is_flag=True,
              help="Also render each image's shading (shading/NNNNN.npz: the object under a black and a "
                   "white texture, its uv per pixel): the data 'undream victims train-adversarial' takes.")
@progress_option
@one_line_errors
def make_dataset_cmd(out: Path, n: int, seed: int, split: str, size: int, spp: int,
                     distribution: str, shading: bool, progress: bool) -> None:
    """Render N images of the built-in assets with their classes and boxes."""
    from undream.training.dataset import DatasetConfig, make_dataset

    local_settings()  # Mitsuba's variant, from UNDREAM_MI_VARIANT (the dataset's own is set around its renders)
    cfg = DatasetConfig(n=n, seed=seed, split=split, size=size, spp=spp, distribution=distribution,
                        shading=shading)
    done = make_dataset(out, cfg, progress=progress, command=_command())
    click.echo(f"wrote {n} images to {done}")


@victims.command("train")
@click.option("--task", required=True, type=click.Choice(["classification", "detection"]))
@click.option("--data", required=True, multiple=True, type=click.Path(path_type=Path),
              help="Training dataset; repeat for a set rendered in parts (the same distribution "
                   "and split under other seeds), trained on as one.")
@click.option("--test", "test", required=True, type=click.Path(path_type=Path),
              help="Held-out dataset, evaluated after training.")
@out_option("Folder to write the model to (save_pretrained layout).")
@seed_option
@click.option("--epochs", default=None, type=click.IntRange(1, 10000),
              help="Training epochs (default: the task's own, see undream.training.train).")
@click.option("--backbone", default=None, type=click.Path(path_type=Path),
              help="Detection: start the backbone from this trained classifier folder.")
@click.option("--threads", default=None, type=click.IntRange(1, 1024),
              help="torch CPU threads (default: torch's choice).")
@click.option("--arch", default=None, type=click.Choice(["resnet", "detr", "yolo"]),
              help="The model: classification trains resnet; detection detr (default) or yolo "
                   "(undream's YOLOv8-shaped detector, from scratch).")
@one_line_errors
def train_cmd(task: str, data: tuple[Path, ...], test: Path, out: Path, seed: int, epochs: int | None,
              backbone: Path | None, threads: int | None, arch: str | None) -> None:
    """Train a bundled-style victim on DATA and evaluate it on TEST."""
    from undream.training.train import TrainConfig, train

    cfg = TrainConfig(task=task, seed=seed, epochs=epochs, backbone=backbone, threads=threads, arch=arch)
    result = train(list(data), test, out, cfg, command=_command())
    click.echo(json.dumps(result["test"], indent=2))
    click.echo(f"wrote {out}")


@victims.command("train-adversarial")
@click.option("--base", required=True,
              help="The classifier to fine-tune: bundled:NAME or a save_pretrained folder.")
@click.option("--data", required=True, multiple=True, type=click.Path(path_type=Path),
              help="Training dataset made with --shading; repeat for a set rendered in parts.")
@click.option("--test", "test", required=True, type=click.Path(path_type=Path),
              help="Held-out dataset made with --shading: clean and robust accuracy, before and after.")
@out_option("Folder to write the model to (save_pretrained layout, training.json, MODEL_CARD.md).")
@seed_option
@click.option("--eps", default="16,50,255", show_default=True,
              help="Budgets (0-255, comma-separated), one drawn per attacked image.")
@click.option("--steps", default=5, show_default=True, type=click.IntRange(1, 1000), help="PGD steps per batch.")
@click.option("--epochs", default=16, show_default=True, type=click.IntRange(1, 10000))
@click.option("--lr", default=1e-3, show_default=True, type=click.FloatRange(min=0, min_open=True))
@click.option("--clean-share", default=0.4, show_default=True, type=click.FloatRange(0, 1, max_open=True),
              help="Share of each batch seen as rendered; the rest is attacked.")
@click.option("--eval-steps", default=20, show_default=True, type=click.IntRange(1, 1000),
              help="PGD steps of the held-out robust accuracy.")
@click.option("--threads", default=None, type=click.IntRange(1, 1024), help="torch CPU threads.")
@one_line_errors
def train_adversarial_cmd(base: str, data: tuple[Path, ...], test: Path, out: Path, seed: int, eps: str,
                          steps: int, epochs: int, lr: float, clean_share: float, eval_steps: int,
                          threads: int | None) -> None:
    """Fine-tune a classifier against textures attacked in the loop (PGD-AT on the texture)."""
    from undream.training.adversarial import AdversarialConfig, train_adversarial

    try:
        budgets = tuple(int(e) for e in eps.split(","))
    except ValueError:
        raise VictimError(f"--eps: budgets must be integers in 1..255, comma-separated; got {eps!r}") from None
    cfg = AdversarialConfig(eps=budgets, steps=steps, epochs=epochs, lr=lr, clean_share=clean_share, seed=seed,
                            eval_steps=eval_steps, threads=threads)
    result = train_adversarial(list(data), test, base, out, cfg, command=_command())
    click.echo(json.dumps({"test": result["test"]["accuracy"], **result["adversarial"]["held_out"]}, indent=2))
    click.echo(f"wrote {out}")


@victims.command("evaluate")
@click.option("--victim", "victim", required=True,
              help="bundled:NAME (e.g. bundled:classifier-v2), a save_pretrained or undream YOLO folder, "
                   "a YOLOv8/YOLO11 *.pt (needs ultralytics) or a hub id.")
@click.option("--data", required=True, type=click.Path(path_type=Path), help="Dataset to score.")
@click.option("--json", "json_out", default=None, type=click.Path(path_type=Path),
              help="Also write the numbers to this JSON file.")
@one_line_errors
def evaluate_cmd(victim: str, data: Path, json_out: Path | None) -> None:
    """Accuracy (classifier) or AP@0.5 (detector) of VICTIM on a dataset."""
    from scheduler.preflight import check_output_files
    from undream.spec.io import atomic_write
    from undream.victims import load_victim
    from undream.training.dataset import load_dataset
    from undream.training.evaluation import evaluate

    check_output_files((("--json", json_out),), inputs=(data, Path(victim)))
    ds = load_dataset(data)  # the cheaper check first
    local = local_settings(render=False)
    result = evaluate(load_victim(victim, offline=local.hf_offline, cache_home=local.cache_home), ds)
    text = json.dumps(result, indent=2)
    click.echo(text)
    if json_out is not None:
        atomic_write(json_out, text + "\n")
