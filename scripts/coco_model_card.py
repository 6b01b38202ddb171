#!/usr/bin/env python3
"""The numbers of coco:centernet's model card (docs/victims.md): parity of undream's
torch port with the official TF.js runtime, detections on real photographs, and
the cost of a forward and a forward + backward pass.

    .venv/bin/python scripts/coco_model_card.py [--photos dog person ...] [--no-parity]

Needs what ./deploy/setup.sh fetches (the model and photos in the cache, and
deploy/tfjs/node_modules for the parity columns). Prints Markdown tables.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from undream.settings import load_local
from undream.victims import Target, load_victim
from undream.victims.coco import COCO_LABELS, MODELS, model_path
from undream.victims.tfjs import GraphModule, read_graph_model

REPO = Path(__file__).resolve().parents[1]
PHOTOS = ("dog", "person", "horses", "giraffe", "kite", "eagle", "bus", "zidane")


def load_photo(cache: Path, name: str) -> torch.Tensor:
    img = Image.open(cache / "photos" / f"{name}.jpg").convert("RGB")
    return torch.from_numpy(np.asarray(img, dtype=np.float32) / 255).permute(2, 0, 1)[None]


def parity(cache: Path, photos: list[str]) -> dict[str, tuple[float, float]]:
    """Per photo: max |Δ class score| and max |Δ box distance| / max |box distance|, torch vs TF.js."""
    spec = MODELS["centernet"]
    size = spec.input_size
    path = model_path("centernet", cache)
    graph = GraphModule(read_graph_model(path), [spec.scores, spec.boxes], spec.input)
    out: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        xs = []
        for name in photos:
            img = Image.open(cache / "photos" / f"{name}.jpg").convert("RGB").resize((size, size), Image.BILINEAR)
            x = torch.from_numpy(np.asarray(img, dtype=np.float32))[None].contiguous()
            x.numpy().astype("<f4").tofile(t / f"{name}.f32")
            xs.append(x)
        job = {"model": str(path), "input": spec.input, "shape": [1, size, size, 3],
               "inputs": [str(t / f"{n}.f32") for n in photos], "outputs": [spec.scores, spec.boxes],
               "out_dir": str(t / "js")}
        (t / "job.json").write_text(json.dumps(job))
        subprocess.run(["node", str(REPO / "deploy" / "tfjs" / "run_graph.cjs"), str(t / "job.json")],
                       check=True, capture_output=True)
        rows = json.loads((t / "js" / "outputs.json").read_text())
        for name, x, row in zip(photos, xs, rows):
            with torch.no_grad():
                ours = graph(x)
            errs = []
            for o in (spec.scores, spec.boxes):
                ref = np.fromfile(t / "js" / row[o]["file"], "<f4").reshape(row[o]["shape"])
                d = float(np.abs(ours[o].numpy() - ref).max())
                errs.append(d if o == spec.scores else d / float(np.abs(ref).max()))
            out[name] = (errs[0], errs[1])
    return out


def timing(victim, threads: int, reps: int = 3) -> tuple[float, float]:
    """Median seconds of predict and of loss + backward on one 512² image with ``threads`` threads."""
    torch.set_num_threads(threads)
    x = torch.rand(1, 3, 512, 512)
    fw, fb = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        victim.predict(x)
        fw.append(time.perf_counter() - t0)
        xg = x.clone().requires_grad_(True)
        t0 = time.perf_counter()
        victim.loss(xg, Target(label=11, box=(100, 100, 300, 300)), "vanish").backward()
        fb.append(time.perf_counter() - t0)
    return float(np.median(fw)), float(np.median(fb))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", nargs="+", default=list(PHOTOS))
    ap.add_argument("--no-parity", action="store_true", help="leave out the TF.js columns (no node needed)")
    args = ap.parse_args()
    home = load_local().cache_home
    cache = Path(home) / "undream"
    victim = load_victim("coco:centernet", cache_home=home)
    par = {} if args.no_parity else parity(cache, args.photos)
    print("| photo | size | detections (score ≥ 0.3) | max abs Δ class score | max rel. Δ box |")
    print("|---|---|---|---|---|")
    for name in args.photos:
        x = load_photo(cache, name)
        pred = victim.predict(x)[0]
        dets = ", ".join(f"{COCO_LABELS[int(lab)]} {float(s):.2f}" for s, lab in zip(pred.scores, pred.labels))
        p = par.get(name)
        cols = (f"{p[0]:.1e}", f"{p[1]:.1e}") if p else ("", "")
        print(f"| {name} | {x.shape[-1]}×{x.shape[-2]} | {dets or 'none'} | {cols[0]} | {cols[1]} |")
    print("\n| threads | predict (s) | loss + backward (s) |\n|---|---|---|")
    for threads in (1, 2):
        fw, fb = timing(victim, threads)
        print(f"| {threads} | {fw:.2f} | {fb:.2f} |")


if __name__ == "__main__":
    main()
