"""Sweeps: a grid over run-config fields, expanded into runs.

A sweep file (YAML)::

    name: bin_park_eps
    run: runs/bin_park_pgd.yaml      # the base run config (relative to this file); or
    # base: {scene: ..., victim: ...}  # the base config inline
    grid:                            # every combination becomes one run
      attack.eps: [50, 100, 200]     # dotted names reach into mappings
      seed: [0, 1]

Runs are named ``<sweep name>-NNN`` in grid order (the last field varies
fastest); each run's config is the base with that combination set.
"""
from __future__ import annotations

import copy
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec import _check as c
from undream.spec.io import read_yaml
from undream.spec.limits import MAX_SWEEP_RUNS
from undream.spec.run import RunConfig, palettes_beside, profile_beside


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: its config, the folder its relative paths start from, its grid values."""

    config: RunConfig
    base_dir: Path
    values: dict[str, Any]


@dataclass(frozen=True)
class Sweep:
    name: str
    runs: list[SweepRun]
    spec: dict[str, Any]  # as written, for the store


def set_dotted(data: dict[str, Any], dotted: str, value: Any, where: str) -> None:
    """Set ``data[a][b]... = value`` for ``dotted`` = "a.b...", copying the mappings on the way
    (the caller's nested mappings are not changed); ``where`` names the field in errors."""
    *parents, leaf = dotted.split(".")
    node = data
    for i, part in enumerate(parents):
        child = node.get(part, {})
        if not isinstance(child, dict):
            raise SpecError(f"{where}: {'.'.join(parents[:i + 1])} is not a mapping")
        node[part] = child = dict(child)
        node = child
    node[leaf] = value


def load_sweep(path: str | Path, max_runs: int = MAX_SWEEP_RUNS) -> Sweep:
    """Parse and expand a sweep file; errors name the file, the field and the run. A grid of more
    than ``max_runs`` runs is refused before it is expanded."""
    path = Path(path)
    data = read_yaml(path)
    try:
        data = dict(c.mapping("sweep", data))
        c.no_extra(data, {"name", "run", "base", "grid"})
        name = c.name("name", c.require(data, "name"))
        if ("run" in data) == ("base" in data):
            raise SpecError("run: give the base run config as a file (run) or inline (base), one of them")
        if "run" in data:
            base_file = path.parent / str(data["run"])
            base, base_dir = read_yaml(base_file), base_file.parent
        else:
            base, base_dir = data["base"], path.parent
        base = dict(c.mapping("base", base))
        grid = dict(c.mapping("grid", c.require(data, "grid")))
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None
    fields = set(RunConfig.__dataclass_fields__)
    for key, values in grid.items():
        if str(key).split(".")[0] not in fields or str(key).split(".")[0] == "name":
            raise SpecError(f"{path}: grid.{key}: not a run-config field (valid: "
                            f"{', '.join(sorted(fields - {'name'}))})")
        if not isinstance(values, list) or not values:
            raise SpecError(f"{path}: grid.{key}: must be a non-empty list of values, got {values!r}")
    size = math.prod(len(v) for v in grid.values())
    if size > max_runs:
        raise SpecError(f"{path}: the grid makes {size} runs, more than the cap of {max_runs} "
                        "(`undream sweep --max-runs N` raises it); nothing recorded")
    runs = []
    for i, combo in enumerate(itertools.product(*grid.values())):
        values = dict(zip(map(str, grid), combo))
        config = copy.deepcopy(base)
        for key, value in values.items():
            set_dotted(config, key, value, f"{path}: grid.{key}")
        config["name"] = f"{name}-{i:03d}"
        try:
            runs.append(SweepRun(RunConfig.from_json(profile_beside(palettes_beside(config, base_dir), base_dir)),
                                 base_dir, values))
        except SpecError as err:
            shown = ", ".join(f"{k}={v!r}" for k, v in values.items())
            raise SpecError(f"{path}: run {i} ({shown}): {err}") from None
    return Sweep(name, runs, {"name": name, "base": base, "grid": grid})


def grid_values(spec: Mapping[str, Any], config: Mapping[str, Any]) -> dict[str, Any]:
    """The grid fields' values in a run's config (for the results table), as the grid writes them
    (``8``, not the stored config's normalised ``8.0``)."""
    out = {}
    for key, values in spec.get("grid", {}).items():
        node: Any = config
        for part in str(key).split("."):
            node = node.get(part) if isinstance(node, Mapping) else None
        listed = values if isinstance(values, list) else []
        out[str(key)] = next((v for v in listed if v == node and type(v) is not bool), node)
    return out
