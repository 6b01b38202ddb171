"""One sequence under every weather preset, the city background and an HDR environment map in
both simulators: a contact sheet and the bundled victims' benign accuracy per row and simulator.

    .venv/bin/python scripts/blender_presets.py --spec examples/bin_orbit.yaml --out /tmp/presets \\
        --sheet docs/presets.png --frames 0 6 12 18 --spp 64

Rows (:data:`ROWS`): the weather presets on the spec's own background, then
``city`` (clear weather, ``background: city``) and ``envmap`` (a procedural
sky map written to ``OUT/sky.exr`` by :func:`write_sky_map`, no download).
``--rows`` picks some of them. Writes ``--sheet`` (rows; columns: the chosen frames, Mitsuba on the
left and Cycles on the right, sRGB) and prints a Markdown table of benign
accuracy (classifier: top-1 is the object's class; detector: the top
detection has the right class and IoU ≥ 0.5 with the mask's box) over every
frame of the sequence, per preset and simulator, plus each preset's mean
linear radiance ratio Cycles / Mitsuba. Renders only; nothing is trained.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from undream.color import linear_to_srgb, to_uint8
from undream.scene.sources import sequence_from_file
from undream.scenedir.init import InitOptions, init_scene
from undream.scenedir.verify import mask_box, read_mask
from undream.sim import make_backend
from undream.spec import WEATHERS

PRESETS = ("clear", "cloudy", "fog", "night", "rain", "snow")
SKY_MAP = "sky.exr"  # in --out; the envmap row's map
# Row name → the environment fields it sets on every frame (SKY_MAP stands for the map's path).
ROWS: dict[str, dict[str, str]] = {**{w: {"weather": w} for w in PRESETS},
                                   "city": {"weather": "clear", "background": "city"},
                                   "envmap": {"weather": "clear", "envmap": SKY_MAP}}


def write_sky_map(path: Path, width: int = 256) -> Path:
    """A procedural equirectangular sky (width × width/2, linear RGB): a blue gradient over a dim
    ground, a warm sun 30° up towards +X and south-west (−Z) haze."""
    from undream.variant import mitsuba

    h = width // 2
    v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(width) + 0.5) / width, indexing="ij")
    theta, phi = np.pi * v, 2 * np.pi * u  # Mitsuba: direction (sin θ sin φ, cos θ, −sin θ cos φ)
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], axis=-1)
    up = np.clip(d[..., 1], 0.0, 1.0)
    sky = np.where(d[..., 1:2] > 0, np.array([0.55, 0.7, 0.95]) * (0.35 + 0.35 * up[..., None]),
                   np.array([0.12, 0.11, 0.10]))
    sun_dir = np.array([np.cos(np.radians(30)), np.sin(np.radians(30)), 0.0])
    sun = np.exp(400 * (d @ sun_dir - 1))[..., None] * np.array([150.0, 130.0, 100.0])  # ≈ 2 W/m² on a face
    haze = np.exp(6 * (d @ np.array([-0.6, 0.0, -0.8]) - 1))[..., None] * 0.3 * (d[..., 1:2] > -0.05)
    mitsuba().Bitmap(np.ascontiguousarray(sky + sun + haze, np.float32)).write(str(path))
    return path


def scene_for(spec: Path, row: str, out: Path, sky_map: Path) -> Path:
    """The spec's sequence with every frame's environment set as ``ROWS[row]`` says, initialised into ``out``."""
    seq = sequence_from_file(spec)
    fields = {k: str(sky_map) if v == SKY_MAP else v for k, v in ROWS[row].items()}
    frames = tuple(dataclasses.replace(f, environment=dataclasses.replace(f.environment, **fields))
                   for f in seq.frames)
    seq = dataclasses.replace(seq, name=f"{seq.name}_{row}", frames=frames)
    if (out / "sequence.json").is_file():
        return out
    return init_scene(seq, out, InitOptions(verify_spp=16))


def render_all(scene: Path, backend: str, spp: int) -> list[np.ndarray]:
    """Every frame with the sequence's initial (grey) texture: H×W×3 linear."""
    from undream.spec import load_sequence

    seq = load_sequence(scene / "sequence.json")
    tex = np.full(seq.texture.shape, 0.5, np.float32)
    sim = make_backend(backend, scene)
    try:
        return [sim.render(f.index, tex, spp, 7 + f.index) for f in seq.frames]
    finally:
        if hasattr(sim, "close"):
            sim.close()


def judge(victim, scene: Path, images: list[np.ndarray]) -> float:
    """Benign accuracy of ``victim`` over ``images`` (linear) of ``scene``."""
    import torch

    from undream.engine.context import class_id
    from undream.metrics import GroundTruth, is_detected
    from undream.spec import load_sequence

    seq = load_sequence(scene / "sequence.json")
    label = class_id(victim, seq.asset.builtin or seq.asset.name, "label")
    hits = []
    with torch.no_grad():
        for f, img in zip(seq.frames, images):
            x = torch.from_numpy(linear_to_srgb(img).transpose(2, 0, 1).copy())[None]
            pred = victim.predict(x)[0]
            if victim.task == "classification":
                hits.append(int(pred.label) == label)
            else:
                box = mask_box(read_mask(scene, f.index))
                gt = GroundTruth.of({"boxes": [box] if box else np.zeros((0, 4)), "labels": [label] if box else []})
                hits.append(bool(is_detected(pred, gt, label)))
    return float(np.mean(hits))


def sheet(rows: dict[str, dict[str, list[np.ndarray]]], frames: list[int], path: Path, zoom: int = 2) -> None:
    """Rows: presets; columns: ``frames`` in Mitsuba, a gap, the same frames in Cycles."""
    first = next(iter(rows.values()))["mitsuba"][0]
    h, w = first.shape[:2]
    tw, th, gap, left, top = w * zoom, h * zoom, 12, 60, 18
    n = len(frames)
    img = Image.new("RGB", (left + 2 * n * tw + gap, top + len(rows) * th), (24, 24, 24))
    draw = ImageDraw.Draw(img)
    draw.text((left + 4, 3), "Mitsuba (path traced)", fill=(230, 230, 230))
    draw.text((left + n * tw + gap + 4, 3), "Blender Cycles (CPU)", fill=(230, 230, 230))
    for r, (preset, by_sim) in enumerate(rows.items()):
        y = top + r * th
        draw.text((4, y + th // 2 - 6), preset, fill=(230, 230, 230))
        for s, sim in enumerate(("mitsuba", "blender")):
            for c, k in enumerate(frames):
                tile = Image.fromarray(to_uint8(linear_to_srgb(by_sim[sim][k]))).resize((tw, th), Image.NEAREST)
                img.paste(tile, (left + s * (n * tw + gap) + c * tw, y))
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", type=Path, default=Path("examples/bin_orbit.yaml"))
    ap.add_argument("--out", type=Path, required=True, help="work folder for the scene directories")
    ap.add_argument("--sheet", type=Path, default=Path("docs/presets.png"))
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 6, 12, 18], help="frame positions on the sheet")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--victims", nargs="*", default=["bundled:classifier", "bundled:detector"])
    ap.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(ROWS), help="rows of the sheet")
    args = ap.parse_args()
    from undream.victims import load_victim

    assert set(PRESETS) <= set(WEATHERS)
    victims = [load_victim(v, device="cpu") for v in args.victims]
    args.out.mkdir(parents=True, exist_ok=True)
    sky_map = write_sky_map(args.out / SKY_MAP) if "envmap" in args.rows else args.out / SKY_MAP
    rows: dict[str, dict[str, list[np.ndarray]]] = {}
    table = []
    for preset in args.rows:
        scene = scene_for(args.spec, preset, args.out / preset, sky_map)
        rows[preset] = {}
        row = {"preset": preset}
        for backend in ("mitsuba", "blender"):
            t0 = time.perf_counter()
            images = rows[preset][backend] = render_all(scene, backend, args.spp)
            row[f"{backend}_seconds_per_frame"] = round((time.perf_counter() - t0) / len(images), 3)
            for v, name in zip(victims, args.victims):
                row[f"{name} {backend}"] = judge(v, scene, images)
        m = np.mean([x.mean() for x in rows[preset]["mitsuba"]])
        b = np.mean([x.mean() for x in rows[preset]["blender"]])
        row["radiance_ratio_cycles_over_mitsuba"] = round(float(b / m), 3)
        print(json.dumps(row), flush=True)
        table.append(row)
    sheet(rows, args.frames, args.sheet)
    cols = [f"{n} {b}" for n in args.victims for b in ("mitsuba", "blender")]
    print("\n| preset | " + " | ".join(cols) + " | Cycles/Mitsuba mean radiance |")
    print("|---" * (len(cols) + 2) + "|")
    for row in table:
        print(f"| {row['preset']} | " + " | ".join(f"{row[c]:.2f}" for c in cols)
              + f" | {row['radiance_ratio_cycles_over_mitsuba']:.3f} |")
    print(f"\nsheet: {args.sheet}")


if __name__ == "__main__":
    main()
