#!/usr/bin/env python
"""What a frame in haze costs against a clear one, and why: kernel time, path length, roulette.

    .venv/bin/python benchmarks/bench_haze.py --scene build/bc/scene --frames 192 250 300 \
        [--before /tmp/haze_before.py] [--spp 32] [--repeats 9]

``--scene``: a scene directory with frames in a medium and their clear twins ``--offset`` frames
earlier (the README's 16-condition job's ``OUT/scene``: frames 192–383 in snow, 0–191 the same views
clear). ``--frames``: the frames in haze to measure. Each frame is loaded from its own file and
rendered by ``mi.render`` (traced every time, so only the kernels' own time is counted: Dr.Jit's
kernel history, the replay of a recorded render costs about that), alternating the integrators, the
first three renders untimed; medians. Three tables:

- kernel time per frame: the clear twin (``path``), ``haze`` and, with ``--before`` (a copy of an
  older ``undream/render/haze.py``, e.g. ``git show 00f5d59:undream/render/haze.py``), that
  integrator under the name ``haze_before``; and the largest difference between their images for
  the same seed (0 where they are bit for bit equal);
- path length: loop iterations a sample makes in the medium and with the medium made vanishingly
  thin (the clear frame's paths, ``σt`` 10⁻⁹): how much more a medium's frame has to trace;
- Russian roulette from an earlier depth (``rr_depth``): kernel time and mean squared error against a
  ``--reference-spp`` render, and the efficiency ``1 / (time × error)`` against the default's.

Run it alone: the load average is printed.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import re
import statistics
import tempfile
from pathlib import Path
from types import ModuleType

import numpy as np


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", required=True, help="a scene directory (frames/sim_NNNN.xml)")
    p.add_argument("--frames", type=int, nargs="+", required=True, help="frames in a medium")
    p.add_argument("--offset", type=int, default=192, help="frame N's clear twin is N - offset")
    p.add_argument("--before", default=None, help="an older haze.py to compare (registered as haze_before)")
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--rr-depths", type=int, nargs="*", default=[5, 3, 2, 1])
    p.add_argument("--reference-spp", type=int, default=1024)
    return p.parse_args(argv)


def _replace_once(text: str, old: str, new: str, where: str) -> str:
    """``text`` with its first ``old`` replaced; exits naming ``where`` when ``old`` is not there (a
    patch that silently missed would time or measure the unpatched thing)."""
    if old not in text:
        raise SystemExit(f"bench_haze: {where} has no {old.strip()!r}")
    return text.replace(old, new, 1)


def _module_from(path: str, name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.NAME = name
    return module


class Frames:
    """Scenes loaded from a frame's file with its integrator renamed or its medium changed."""

    def __init__(self, mi: ModuleType, scene: Path) -> None:
        self.mi, self.dir = mi, scene / "frames"

    def load(self, index: int, integrator: str | None = None, extra: str = "", sigma_t: str | None = None):
        path = self.dir / f"sim_{index:04d}.xml"
        xml = path.read_text()
        if integrator is not None:
            xml = _replace_once(xml, 'type="haze"', f'type="{integrator}"', f"{path} (a frame in a medium?)")
        if extra:
            xml = _replace_once(xml, '<integer name="max_depth"', extra + '<integer name="max_depth"', str(path))
        if sigma_t is not None:
            xml, n = re.subn(r'<float name="sigma_t" value="[^"]*"/>',
                             f'<float name="sigma_t" value="{sigma_t}"/>', xml)
            if n == 0:
                raise SystemExit(f"bench_haze: {path} has no sigma_t (a frame in a medium?)")
        # written beside the frame's own file: its relative paths (meshes, textures) resolve
        with tempfile.NamedTemporaryFile("w", suffix=".xml", dir=self.dir, delete=False) as f:
            f.write(xml)
        try:
            return self.mi.load_file(f.name)
        finally:
            os.unlink(f.name)

    def clear_twin(self, index: int, offset: int):
        """The clear frame ``offset`` frames before ``index``, loaded from its own file."""
        return self.mi.load_file(str(self.dir / f"sim_{index - offset:04d}.xml"))


def kernel_ms(mi: ModuleType, scene, spp: int, seed: int) -> tuple[float, np.ndarray]:
    """The image, and the milliseconds its kernels ran (Dr.Jit's kernel history)."""
    import drjit as dr

    dr.kernel_history()
    image = np.array(mi.render(scene, spp=spp, seed=seed))
    return sum(k.get("execution_time", 0.0) for k in dr.kernel_history()), image


def _timed(mi, scenes: dict, spp: int, repeats: int) -> tuple[dict, dict]:
    """Each scene's median kernel milliseconds and its timed images (seeds 3, 4, …), the scenes taking
    turns; the first three renders of each (seeds 0–2) untimed."""
    times: dict = {k: [] for k in scenes}
    images: dict = {k: [] for k in scenes}
    for r in range(repeats + 3):
        for key, scene in scenes.items():
            ms, image = kernel_ms(mi, scene, spp, r)
            if r >= 3:
                times[key].append(ms)
                images[key].append(image)
    return {k: statistics.median(v) for k, v in times.items()}, images


def _register_length(mi: ModuleType) -> None:
    """``haze`` with its image replaced by the loop iterations of each sample (a path's length),
    registered as ``haze_length`` (its source must exist while the class is made: @dr.syntax reads it)."""
    import undream.render.haze as haze

    where = haze.__file__
    source = Path(where).read_text()
    source = _replace_once(source, 'NAME = "haze"', 'NAME = "haze_length"', where)
    source = _replace_once(source, "            while active:\n",
                           "            length = mi.Float(0.0)\n            while active:\n"
                           "                length += dr.select(active, 1.0, 0.0)\n", where)
    source = _replace_once(source, "            return result, valid_ray, []",
                           "            return mi.Spectrum(length), valid_ray, []", where)
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(source)
    try:
        _module_from(f.name, "haze_length").register(mi)
    finally:
        os.unlink(f.name)


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    import drjit as dr

    from undream.render.haze import register
    from undream.settings import load_local
    from undream.variant import mitsuba

    mi = mitsuba(load_local().mi_variant)
    register(mi)
    before = _module_from(args.before, "haze_before") if args.before else None
    if before is not None:
        before.register(mi)
    _register_length(mi)
    frames = Frames(mi, Path(args.scene))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    print(f"load average before: {os.getloadavg()[0]:.2f}; {args.spp} spp, medians of {args.repeats}")

    print("\n| frame | clear (path) | haze | haze / clear |"
          + (" haze_before | haze / haze_before | largest difference, same seed |" if before else ""))
    print("|---:|---:|---:|---:|" + ("---:|---:|---:|" if before else ""))
    for index in args.frames:
        scenes = {"clear": frames.clear_twin(index, args.offset), "haze": frames.load(index)}
        if before is not None:
            scenes["before"] = frames.load(index, "haze_before")
        t, images = _timed(mi, scenes, args.spp, args.repeats)
        row = f"| {index} | {t['clear']:.1f} ms | {t['haze']:.1f} ms | {t['haze'] / t['clear']:.2f}× |"
        if before is not None:
            largest = float(np.abs(images["haze"][0] - images["before"][0]).max())
            row += f" {t['before']:.1f} ms | {t['haze'] / t['before']:.2f} | {largest:.2g} |"
        print(row)

    print("\n| frame | path length in the medium | without it (σt 10⁻⁹) | ratio | sky pixels (length 1 without) |")
    print("|---:|---:|---:|---:|---:|")
    for index in args.frames:
        medium = np.array(mi.render(frames.load(index, "haze_length"), spp=args.spp))[..., 0]
        thin = np.array(mi.render(frames.load(index, "haze_length", sigma_t="1e-9"), spp=args.spp))[..., 0]
        print(f"| {index} | {medium.mean():.2f} | {thin.mean():.2f} | {medium.mean() / thin.mean():.2f} "
              f"| {100 * (thin < 1.01).mean():.0f} % |")

    print(f"\n| frame | rr_depth | kernel time | against clear | MSE against {args.reference_spp} spp | efficiency |")
    print("|---:|---:|---:|---:|---:|---:|")
    for index in args.frames:
        reference = np.array(mi.render(frames.load(index), spp=args.reference_spp, seed=10_000))
        scenes = {"clear": frames.clear_twin(index, args.offset)}
        scenes.update({rr: frames.load(index, extra=f'<integer name="rr_depth" value="{rr}"/>')
                       for rr in args.rr_depths})
        t, images = _timed(mi, scenes, args.spp, args.repeats)
        e = {k: float(np.mean([((image - reference) ** 2).mean() for image in v])) for k, v in images.items()}
        first = args.rr_depths[0]
        for rr in args.rr_depths:
            print(f"| {index} | {rr} | {t[rr]:.1f} ms | {t[rr] / t['clear']:.2f}× | {e[rr]:.3g} "
                  f"| {(t[first] * e[first]) / (t[rr] * e[rr]):.2f} |")
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
