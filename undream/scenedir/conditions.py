"""Multi-condition runs: one sequence made of several scenes of one object.

A run's ``conditions`` block (:class:`undream.spec.run.ConditionsConfig`)
names scenes (spec files or scene directories) or grids over fields of the
run's spec file. Each becomes a :class:`Sequence`; :func:`compose` checks that
they show the same object (mesh, UVs and texture size) and chains their frames
into one sequence whose ``conditions`` say which frames were which scene, so
that ``undream init`` writes one scene directory and everything downstream (the
farm, the transports, the evaluation) sees an ordinary, longer sequence. Each
frame keeps its own camera, pose and environment. Background props are placed
once, from the first condition's seed and clear of every condition's lines of
sight: one place under several conditions (and no prop moves when a render
switches conditions, which would rebuild the scene's BVH).
"""
from __future__ import annotations

import copy
import itertools
import re
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from undream.errors import AssetError, SpecError, UndreamError
from undream.scene.builtin import asset_mesh
from undream.scene.layout import SEQUENCE_FILE
from undream.scene.sources import sequence_from_file
from undream.spec import Condition, Sequence, load_sequence
from undream.spec.io import join_against, read_yaml
from undream.spec.run import RunConfig, plain_grid_value


def condition_sources(config: RunConfig, base_dir: Path) -> list[Path]:
    """Every scene a run names (``scene`` and ``conditions.scenes``), as absolute paths."""
    names = [config.scene] + list(config.conditions.scenes if config.conditions else ())
    return [join_against(name, base_dir).resolve() for name in names]


def conditions_sequence(config: RunConfig, base_dir: Path, cache_dir: str | Path | None = None) -> Sequence:
    """The multi-condition sequence of ``config`` (which has a ``conditions`` block); SpecError
    naming the field, condition or file otherwise. Reads the specs and meshes; writes nothing.
    ``cache_dir``: undream's cache folder, for the specs' ``asset:NAME``s."""
    assert config.conditions is not None
    base, *more = condition_sources(config, base_dir)
    parts: list[tuple[str, Sequence]] = []
    grids = config.conditions.placed_grids()
    for where, grid in grids:
        parts += grid_sequences(base, grid, where, cache_dir)
    if not grids:
        parts.append((_slug(base.stem if base.is_file() else base.name), _read(base, cache_dir)))
    for i, src in enumerate(more):
        try:
            parts.append((_slug(src.stem if src.is_file() else src.name), _read(src, cache_dir)))
        except UndreamError as err:
            raise type(err)(f"conditions.scenes[{i}]: {err}") from None
    names = [name for name, _ in parts]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise SpecError(f"conditions: two conditions are named {', '.join(repeated)} (a scene by its file or "
                        "folder name, a grid's by its fields and values); rename a scene or give the grids "
                        "other fields")
    unknown = [h for h in config.conditions.holdout if h not in names]
    if unknown:
        raise SpecError(f"conditions.holdout: {', '.join(map(repr, unknown))} is not a condition of the run "
                        f"({', '.join(names)})")
    return compose(parts, config.name)


def grid_sequences(spec_file: Path, grid: Mapping[str, tuple[Any, ...]],
                   where: str = "conditions.grid", cache_dir: str | Path | None = None) -> list[tuple[str, Sequence]]:
    """One sequence per combination of ``grid``'s values, each the spec file with those values set
    (``where``: the grid's place in the run config, named in errors)."""
    if not spec_file.is_file() or spec_file.suffix.lower() not in (".yaml", ".yml"):
        raise SpecError(f"{where}: needs scene to be a YAML spec file, got {spec_file}")
    spec = read_yaml(spec_file)
    if not isinstance(spec, dict):
        raise SpecError(f"{spec_file}: a spec must be a mapping")
    from undream.scene.trajectory import sequence_from_trajectory  # scipy: only where a grid is expanded

    out = []
    for values in itertools.product(*grid.values()):
        point = dict(zip(grid, values))
        name = "-".join(f"{key.rsplit('.', 1)[-1]}_{_value_slug(v)}" for key, v in point.items())
        data = copy.deepcopy(spec)
        for key, value in point.items():
            _set(data, key, plain_grid_value(value), where)
        try:
            seq = sequence_from_trajectory(data, base_dir=spec_file.parent, cache_dir=cache_dir)
            out.append((name, _anchored(seq, spec_file.parent)))
        except UndreamError as err:
            raise type(err)(f"{where} ({name}): {spec_file}: {err}") from None
    return out


def _set(spec: dict[str, Any], dotted: str, value: Any, where: str) -> None:
    keys = dotted.split(".")
    node = spec
    for i, key in enumerate(keys[:-1]):
        if node.get(key) is None:
            node[key] = {}
        if not isinstance(node[key], dict):
            raise SpecError(f"{where}.{dotted}: the spec's {'.'.join(keys[:i + 1])} is not a mapping "
                            "(a per-frame list cannot take one value)")
        node = node[key]
    node[keys[-1]] = value


def _value_slug(value: Any) -> str:
    """A grid value in a condition's name: ``2.5`` → ``2p5``, ``(2.5, 6, -1)`` → ``2p5_6_-1``."""
    return "_".join(_slug(str(x)) for x in value) if isinstance(value, tuple) else _slug(str(value))


def _slug(text: str) -> str:
    """A condition name from a file name or value: letters, digits, '_' and '-' ('.' → 'p')."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", text.replace(".", "p"))[:64] or "condition"


def _read(src: Path, cache_dir: str | Path | None = None) -> Sequence:
    """A condition's sequence, every file it names absolute: a scene directory's own meshes and
    environment maps, a spec file's relative paths resolved against its folder."""
    if (src / SEQUENCE_FILE).is_file():
        seq = load_sequence(src / SEQUENCE_FILE)
        if seq.conditions:
            raise SpecError(f"{src}: is itself a multi-condition scene; name its conditions' scenes instead")
        asset = replace(seq.asset, mesh=str(src / "meshes" / "object.ply"), scale=1.0)  # written scaled
        tex = asset.texture
        if tex is not None and isinstance(tex.init, str):
            asset = replace(asset, texture=replace(tex, init=str(src / "textures" / f"{tex.name}.png")))
        actors = tuple(replace(a, mesh=str(src / "meshes" / f"{a.name}.ply"), scale=1.0) for a in seq.actors)
        return _anchored(replace(seq, asset=asset, actors=actors), src)
    if not src.is_file():
        raise SpecError(f"{src}: is neither a scene directory nor a spec file")
    return _anchored(sequence_from_file(src, cache_dir), src.parent)


def _anchored(seq: Sequence, base_dir: Path) -> Sequence:
    """``seq`` with its texture image and environment maps as absolute paths (meshes already are)."""
    tex = seq.asset.texture
    if tex is not None and isinstance(tex.init, str):
        seq = replace(seq, asset=replace(seq.asset, texture=replace(tex, init=str(join_against(tex.init, base_dir)))))
    frames = tuple(f if f.environment.envmap is None else
                   replace(f, environment=replace(f.environment,
                                                  envmap=str(join_against(f.environment.envmap, base_dir))))
                   for f in seq.frames)
    return replace(seq, frames=frames)


def compose(parts: list[tuple[str, Sequence]], name: str) -> Sequence:
    """The conditions' frames chained into one sequence (indices 0, 1, ...; times running on).

    The first condition's object (mesh, scale, texture) is the run's; every other must show the
    same mesh with the same triangles, UVs and texture size (a texel lands on the same spot of the
    surface everywhere). Actors of the same name must be the same asset. SpecError naming the
    condition otherwise; a per-frame (animated) object mesh is refused.
    """
    first_name, first = parts[0]
    if first.asset.per_frame:
        raise SpecError(f"condition {first_name!r}: a per-frame (animated) object mesh cannot be part of a "
                        "multi-condition run")
    reference = _mesh(first_name, first)
    actors = {a.name: a for a in first.actors}
    frames, conditions, t0 = [], [], 0.0
    for cname, seq in parts:
        if seq is not first:
            _same_object(cname, seq, first_name, first, reference)
            for a in seq.actors:
                if actors.setdefault(a.name, a) != a:
                    raise SpecError(f"condition {cname!r}: actor {a.name!r} differs from the one of the same name "
                                    "in an earlier condition; give it another name")
        for f in seq.frames:
            frames.append(replace(f, index=len(frames), time=t0 + (f.time - seq.frames[0].time)))
        t0 = frames[-1].time + 1.0 / seq.fps
        conditions.append(Condition(cname, len(seq.frames)))
    return Sequence(name=name, asset=first.asset, frames=tuple(frames), actors=tuple(actors.values()),
                    fps=first.fps, source="conditions", seed=first.seed, conditions=tuple(conditions))


def _mesh(cname: str, seq: Sequence) -> Any:
    try:
        return asset_mesh(seq.asset)
    except AssetError as err:
        raise AssetError(f"condition {cname!r}: asset.mesh: {err}") from None


def _same_object(cname: str, seq: Sequence, first_name: str, first: Sequence, reference: Any) -> None:
    if seq.asset.per_frame:
        raise SpecError(f"condition {cname!r}: a per-frame (animated) object mesh cannot be part of a "
                        "multi-condition run")
    tex, ref_tex = seq.texture, first.texture
    if (tex.resolution, tex.uv_scale, tex.name) != (ref_tex.resolution, ref_tex.uv_scale, ref_tex.name):
        raise SpecError(f"condition {cname!r}: its texture ({tex.name}, {tex.resolution[0]}×{tex.resolution[1]}, "
                        f"uv_scale {tex.uv_scale}) differs from condition {first_name!r}'s ({ref_tex.name}, "
                        f"{ref_tex.resolution[0]}×{ref_tex.resolution[1]}, uv_scale {ref_tex.uv_scale}): "
                        "a multi-condition run attacks one texture")
    mesh = _mesh(cname, seq)
    same = (mesh.n_vertices == reference.n_vertices and np.array_equal(mesh.faces, reference.faces)
            and np.allclose(mesh.uvs, reference.uvs, atol=1e-6)
            and np.allclose(mesh.vertices, reference.vertices, atol=1e-6))
    if not same:
        raise SpecError(f"condition {cname!r}: its object ({seq.asset.mesh}, {mesh.n_vertices} vertices, "
                        f"{mesh.n_faces} triangles) is not condition {first_name!r}'s ({first.asset.mesh}, "
                        f"{reference.n_vertices} vertices, {reference.n_faces} triangles) with the same shape and "
                        "UVs: a multi-condition run attacks one mesh")
