"""Smoke training of undream's YOLO-style detector on synthetic squares: does the loop converge?

Nothing is rendered: the training and held-out sets are coloured squares on noise
(:func:`undream.training.yolo.synthetic_squares`, different seeds), wrapped as in-memory
:class:`undream.training.dataset.Dataset` objects and trained by the same
:func:`undream.training.train.fit` as ``undream victims train --task detection --arch yolo``
(augmentation, AdamW, cosine schedule). Prints the per-epoch loss and one JSON line with the
held-out numbers of :func:`undream.training.train.evaluate` (AP@0.5 by pycocotools).

    PYTHONPATH=. python scripts/yolo_smoke.py --epochs 20 --n 384 --threads 1
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from undream.training.dataset import CLASSES, Dataset
from undream.training.train import TrainConfig, build_model, evaluate, fit, preprocess_config
from undream.training.yolo import synthetic_squares
from undream.victims.dense import DenseDetector


def squares_dataset(n: int, size: int, seed: int) -> Dataset:
    """``n`` synthetic images (one square each) as a :class:`Dataset` (uint8 images, classes 0-2)."""
    images, boxes, labels = synthetic_squares(n, size, torch.Generator().manual_seed(seed), max_objects=1)
    pixels = (images.permute(0, 2, 3, 1) * 255).round().to(torch.uint8).numpy()
    records = [{"name": CLASSES[int(y)], "params": {"environment": {"weather": "synthetic"}}} for y in labels[:, 0]]
    return Dataset(pixels, labels[:, 0].numpy().astype(np.int64), boxes[:, 0].numpy().astype(np.float32),
                   records, {"config": {"n": n, "seed": seed, "size": size}})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--n", type=int, default=384, help="training images (held out: a quarter as many)")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    train_ds = squares_dataset(args.n, args.size, args.seed)
    test_ds = squares_dataset(max(1, args.n // 4), args.size, args.seed + 1000)
    cfg = TrainConfig(task="detection", arch="yolo", epochs=args.epochs, seed=args.seed,
                      threads=args.threads, input_size=args.size)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg)
    start = time.perf_counter()
    seconds = fit(model, train_ds, cfg, print)
    victim = DenseDetector(model, CLASSES, preprocess_config(args.size), name="smoke")
    result = evaluate(victim, test_ds)
    result.pop("ap50_per_class")
    print(json.dumps({"train_seconds": round(seconds, 1), "total_seconds": round(time.perf_counter() - start, 1),
                      "parameters": sum(p.numel() for p in model.parameters()), "epochs": args.epochs,
                      "n_train": args.n, **result}))


if __name__ == "__main__":
    main()
