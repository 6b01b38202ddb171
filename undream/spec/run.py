"""The attack run configuration (``RUN.yaml``): frozen, validated, JSON round trip.

No heavy imports. The attack block is typed (:class:`undream.spec.attack.AttackConfig`) and
complete: every field the attack runs with, its seed included (the run's seed unless the block gives
its own), so a stored run config says everything about the run and every reader reads the same
numbers through :class:`RunConfig` (``RunSnapshot.run_config`` for a stored run).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping

from undream.errors import SpecError
from undream.spec import _check as c
from undream.spec.attack import AttackConfig
from undream.spec.defence import DefenceConfig, typed_defence
from undream.spec.io import read_yaml
from undream.spec.limits import MAX_FRAMES, bounded
from undream.spec.printing import check_gamut, check_profile
from undream.spec.physical import PrintEotConfig, RegulariseConfig, typed

TASK_LOSSES = {"classification": ("ce", "targeted_ce", "dlr", "margin"), "detection": ("vanish", "mislabel", "box")}
ALL_LOSSES = tuple(k for kinds in TASK_LOSSES.values() for k in kinds)
SIMULATORS = ("mitsuba", "blender", "unreal")  # undream.sim backends a run may name


@dataclass(frozen=True)
class RunConfig:
    """One attack run.

    ``scene`` is a scene directory written by ``undream init`` or a spec file
    (YAML, Unreal export, sequence.json) that the run initialises first.
    ``label`` is the object's true class name in the victim's labels (default:
    the name of the built-in asset); ``target_label`` the class a targeted
    loss pushes towards. Samples per pixel: ``sim_spp`` for the simulator's
    frames during the attack, ``grad_spp`` for the gradient renders,
    ``eval_spp`` for the benign and adversarial evaluations (``grad_spp``
    16 by default: with the captured transport its samples are paid once per
    capture, and scripts/speed_accuracy.py measured 16 as cheap as 8 per
    iteration, with a truer gradient and a stronger attack on held-out
    views). ``gradient``:
    ``auto`` computes each frame's texture gradient from its captured
    texel → pixel transport where the gradient scene is linear in the
    texture (else by Mitsuba's prb backward pass), ``transport`` requires
    that, ``prb`` always renders; ``transport_refresh``: capture each frame
    again with a new sample pattern every this many passes over the attacked
    frames (iterations, unless ``attack.frames_per_step`` draws minibatches:
    :func:`undream.engine.context.refresh_iterations`). ``sim``: the
    simulator that renders the frames the victim sees, during the attack and
    in the evaluation (``mitsuba``, embedded; ``blender``: Cycles, needs
    Blender's Python, see :mod:`undream.sim.blender`); the texture gradient
    always comes from Mitsuba's gradient scene. ``victim_batch``: the most
    frames the victim sees in one pass (forward and backward) during the
    attack and the evaluation (a job's frames in order; results agree to float
    rounding whatever the batches). ``conditions``: attack one texture over
    several scenes of the object at once (:class:`ConditionsConfig`).
    ``media``: with the crop, ``auto`` renders an attack window in fog, rain or
    snow without the medium and maps it into the medium's look
    (:mod:`undream.render.media`), ``exact`` path traces the medium; the
    evaluation renders whole frames with the medium either way.
    ``regularise``: regularisers subtracted from the victim's loss (smoothness, printability,
    camouflage; :class:`undream.spec.physical.RegulariseConfig`); ``eot_print``: per-frame draws of
    a print's colour shift and blur and of camera noise (:class:`undream.spec.physical.PrintEotConfig`).
    ``defence``: input transforms in front of the victim (JPEG, smoothing, bit depth, resize-and-pad),
    how the attack differentiates through them and whether it does at all; the evaluation judges the
    defended victim (:class:`undream.spec.defence.DefenceConfig`).
    """

    scene: str
    name: str = "run"
    victim: str = "bundled:classifier"
    loss: str = "ce"
    label: str | None = None
    target_label: str | None = None
    # A mapping (as in RUN.yaml) is parsed into an AttackConfig, seed = the run's unless given;
    # omitted: DEFAULT_ATTACK.
    attack: AttackConfig = None  # type: ignore[assignment]
    sim_spp: int = 16
    grad_spp: int = 16
    eval_spp: int = 32
    seed: int = 0
    device: str = "cpu"
    torch_threads: int = 1  # the victim's CPU threads; Dr.Jit renders on the rest
    victim_batch: int = 32  # frames per victim pass (forward and backward), at most: a memory bound
    store: str | None = None  # SQLAlchemy URL; default: SQLite in the output directory
    gradient: str = "auto"  # auto | transport | prb
    transport_refresh: int = 5
    crop: str = "auto"  # auto | off: an iteration renders the object's window on a base (undream.engine.crops)
    crop_margin: float = 0.25  # the window: the object's box grown by this × its longer side on every side
    # frames of fewer pixels are rendered whole by ``crop: auto`` (0: every frame with a window): at 64 px
    # a window's base and first recording cost what its uses save (docs/performance.md, Crop rendering)
    crop_min_pixels: int = 128 * 128
    media: str = "auto"  # auto | exact: a window in fog, rain or snow rendered clear and mapped (undream.render.media)
    holdout: Any = "auto"  # frames the attack never sees, evaluated apart: see split_frames
    eot: Mapping[str, float] | None = None  # camera and light jitter per iteration: see EOT_FIELDS
    sim: str = "mitsuba"  # the simulator backend: one of SIMULATORS
    # A mapping (as in RUN.yaml) is parsed into a ConditionsConfig; None: the one scene.
    conditions: "ConditionsConfig | None" = None
    # default | none | PATH.icc: each step's texture projected into a CMYK printer's gamut (undream.printing.gamut)
    gamut: str = "none"
    # Mappings (as in RUN.yaml) are parsed into these; None: no regulariser, no print-and-capture EOT.
    regularise: RegulariseConfig | None = None
    eot_print: PrintEotConfig | None = None
    # A list or mapping (as in RUN.yaml) is parsed into a DefenceConfig; None: the victim undefended.
    defence: DefenceConfig | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.scene, str) or not self.scene:
            raise c.fail("scene", self.scene, "must be a scene directory or a spec file")
        c.name("name", self.name)
        if not isinstance(self.victim, str) or not self.victim:
            raise c.fail("victim", self.victim, "must be a hub id, a folder or bundled:NAME")
        c.choice("loss", self.loss, ALL_LOSSES)
        for f in ("label", "target_label"):
            v = getattr(self, f)
            if v is not None and not isinstance(v, str):
                raise c.fail(f, v, "must be a class name")
        if self.loss in ("targeted_ce", "mislabel") and self.target_label is None:
            raise c.fail("target_label", None, f"is required by the targeted loss {self.loss!r}")
        for f in ("sim_spp", "grad_spp", "eval_spp", "seed"):
            bounded(f, getattr(self, f))
        object.__setattr__(self, "attack", self._typed_attack())
        c.integer("torch_threads", self.torch_threads, 1, 1024)
        c.integer("victim_batch", self.victim_batch, 1, 4096)
        c.choice("gradient", self.gradient, ("auto", "transport", "prb"))
        c.integer("transport_refresh", self.transport_refresh, 1, 10**6)
        c.choice("crop", self.crop, ("auto", "off"))
        c.integer("crop_min_pixels", self.crop_min_pixels, 0, 10**9)
        c.choice("media", self.media, ("auto", "exact"))
        if not 0.0 <= c.finite("crop_margin", self.crop_margin) <= 4.0:
            raise c.fail("crop_margin", self.crop_margin, "must be between 0 and 4 (× the object's box)")
        if not isinstance(self.device, str):
            raise c.fail("device", self.device, "must be a torch device string such as 'cpu'")
        _check_holdout(self.holdout)
        if self.eot is not None:
            object.__setattr__(self, "eot", _check_eot(self.eot))
            if self.gradient == "transport":
                raise c.fail("gradient", self.gradient, "cannot be 'transport' with eot: a captured transport "
                             "holds each frame's own camera and light; use auto or prb")
            if self.sim != "mitsuba":
                raise c.fail("eot", self.eot, f"needs sim: mitsuba (the {self.sim!r} simulator cannot move "
                             "the camera and light per render)")
        c.choice("sim", self.sim, SIMULATORS)
        check_gamut(self.gamut)
        if self.conditions is not None and not isinstance(self.conditions, ConditionsConfig):
            object.__setattr__(self, "conditions", ConditionsConfig.from_json(self.conditions))
        object.__setattr__(self, "regularise", typed(RegulariseConfig, self.regularise))
        object.__setattr__(self, "eot_print", typed(PrintEotConfig, self.eot_print))
        object.__setattr__(self, "defence", typed_defence(self.defence))

    def _typed_attack(self) -> AttackConfig:
        if isinstance(self.attack, AttackConfig):
            return self.attack
        attack = DEFAULT_ATTACK if self.attack is None else c.mapping("attack", self.attack)
        if "name" not in attack:
            raise c.fail("attack.name", None, "is required")
        return AttackConfig.from_dict({**attack, "seed": attack.get("seed", self.seed)})

    def to_json(self) -> dict[str, Any]:
        """Every field, the attack block complete (its defaults filled in): what the store keeps."""
        d = asdict(self)
        d["conditions"] = None if self.conditions is None else self.conditions.to_json()
        for name in ("regularise", "eot_print", "defence"):
            part = getattr(self, name)
            d[name] = None if part is None else part.to_json()
        return d

    def split(self, sequence: Any) -> "Split":
        """The run's frames of ``sequence`` (an :class:`undream.spec.Sequence`) split by
        :func:`split_frames` (per condition) and ``conditions.holdout``."""
        return split_conditions(self.holdout, sequence.condition_ranges(),
                                () if self.conditions is None else self.conditions.holdout)

    @classmethod
    def from_json(cls, d: Any) -> "RunConfig":
        d = c.mapping("run", d)
        c.no_extra(d, set(cls.__dataclass_fields__))
        c.require(d, "scene")
        return cls(**d)


DEFAULT_ATTACK = {"name": "pgd", "eps": 8.0, "steps": 10}  # a run config without an attack block


@dataclass(frozen=True)
class ConditionsConfig:
    """A multi-condition run's scenes: ``scene`` and ``scenes``, or ``scene`` over ``grid``.

    ``grid``: dotted fields of the ``scene`` spec file (``environment.weather``,
    ``camera.path.height``, ...) → values; each combination is one condition
    (the spec with those values), named ``weather_rain-height_2`` from the
    fields' last parts and the values. Without grids, ``scene`` itself is the
    first condition. ``grids``: more grids over the same spec file, each a
    product of its own values, their conditions after ``grid``'s (nights under
    eight lamps beside days under three weathers, say, which one product would
    multiply). ``scenes``: more spec files or scene directories, one
    condition each (named by their file or folder name). Every condition shows
    the same mesh with the same UVs and texture size; the attack's frames are
    all of theirs, and a minibatch draws across them. ``holdout``: names of
    conditions never attacked, judged apart (``held_out_conditions`` in the
    results); ``holdout`` of the run holds views out within each attacked one.
    """

    grid: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
    grids: tuple[Mapping[str, tuple[Any, ...]], ...] = ()
    scenes: tuple[str, ...] = ()
    holdout: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "grid", _checked_grid("conditions.grid", self.grid))
        if isinstance(self.grids, (str, bytes, Mapping)) or not isinstance(self.grids, (list, tuple)):
            raise c.fail("conditions.grids", self.grids, "must be a list of grids (mappings of field → values)")
        grids = tuple(_checked_grid(f"conditions.grids[{i}]", g) for i, g in enumerate(self.grids))
        for i, g in enumerate(grids):
            if not g:
                raise c.fail(f"conditions.grids[{i}]", {}, "must name at least one field")
        object.__setattr__(self, "grids", grids)
        for name in ("scenes", "holdout"):
            items = getattr(self, name)
            if isinstance(items, (str, bytes)) or not isinstance(items, (list, tuple)):
                raise c.fail(f"conditions.{name}", items, "must be a list")
            for i, item in enumerate(items):
                if not isinstance(item, str) or not item:
                    raise c.fail(f"conditions.{name}[{i}]", item, "must be a non-empty string")
            object.__setattr__(self, name, tuple(items))
        if not self.placed_grids() and not self.scenes:
            raise c.fail("conditions", {}, "needs a grid or scenes (a run of one scene has no conditions block)")
        self._check_count()
        if len(set(self.holdout)) != len(self.holdout):
            raise c.fail("conditions.holdout", list(self.holdout), "must name each condition once")

    def _check_count(self) -> None:
        """Refuse, before any grid is expanded, more conditions than a run has frames: each condition
        holds a frame at least, and a grid of millions of combinations would otherwise be built
        spec by spec before the composed sequence's frame bound refused it."""
        sizes = [(where, math.prod(len(values) for values in grid.values())) for where, grid in self.placed_grids()]
        total = sum(size for _, size in sizes) + len(self.scenes) + (0 if sizes else 1)
        if total > MAX_FRAMES:
            counts = ", ".join(f"{where} {size:,}" for where, size in sizes)
            raise SpecError(f"conditions: {total:,} conditions ({counts}) is more than a run's {MAX_FRAMES:,} frames "
                            "(each condition holds at least one); split the grid into runs or give its fields "
                            "fewer values")

    def placed_grids(self) -> list[tuple[str, Mapping[str, tuple[Any, ...]]]]:
        """Every grid in the order its conditions come (``grid`` when given, then ``grids``), each with
        its place in the run config, which errors about it name."""
        placed = [("conditions.grid", self.grid)] if self.grid else []
        return placed + [(f"conditions.grids[{i}]", grid) for i, grid in enumerate(self.grids)]

    def to_json(self) -> dict[str, Any]:
        grids = {"grids": [_plain_grid(g) for g in self.grids]} if self.grids else {}  # stored configs as before
        return {"grid": _plain_grid(self.grid), **grids, "scenes": list(self.scenes), "holdout": list(self.holdout)}

    @classmethod
    def from_json(cls, d: Any) -> "ConditionsConfig":
        d = c.mapping("conditions", d)
        with c.at("conditions"):
            c.no_extra(d, {"grid", "grids", "scenes", "holdout"})
        return cls(**d)


def _checked_grid(where: str, grid: Any) -> dict[str, tuple[Any, ...]]:
    """``grid`` (dotted spec field → non-empty list of distinct values) checked, values as kept."""
    checked = {}
    for key, values in c.mapping(where, grid).items():
        if not isinstance(key, str) or not key or not all(part.isidentifier() for part in key.split(".")):
            raise c.fail(where, key, "keys must be dotted spec fields such as environment.weather")
        if isinstance(values, (str, bytes)) or not isinstance(values, (list, tuple)) or not values:
            raise c.fail(f"{where}.{key}", values, "must be a non-empty list of values")
        values = [_grid_value(f"{where}.{key}", v) for v in values]
        if len(set(map(str, values))) != len(values):
            raise c.fail(f"{where}.{key}", [plain_grid_value(v) for v in values], "must not repeat a value")
        checked[key] = tuple(values)
    return checked


def _plain_grid(grid: Mapping[str, tuple[Any, ...]]) -> dict[str, list[Any]]:
    return {k: [plain_grid_value(x) for x in v] for k, v in grid.items()}


def _grid_value(where: str, v: Any) -> Any:
    """One value of a grid's field ``where`` (``conditions.grid.<key>``): a string, a number, or a list
    of numbers (a vector field such as ``environment.lamp_offset``), kept as a tuple."""
    def number(x: Any) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    if isinstance(v, str) or number(v):
        return v
    if isinstance(v, (list, tuple)) and v and all(number(x) for x in v):
        return tuple(v)
    raise c.fail(where, v, "values must be strings, numbers or lists of numbers")


def plain_grid_value(v: Any) -> Any:
    """A grid value as JSON, YAML and spec files hold it (a tuple as a list)."""
    return list(v) if isinstance(v, tuple) else v


# eot: field → (largest value, unit and meaning). Each iteration draws, per frame, a camera shift
# uniform in ±camera_shift_m on each axis, camera and sun turns uniform in ±deg about random axes,
# and a light factor uniform in [1 - light_scale, 1 + light_scale] (undream.render.jitter).
EOT_FIELDS = {"camera_shift_m": (10.0, "metres"), "camera_turn_deg": (45.0, "degrees"),
              "sun_turn_deg": (90.0, "degrees"), "light_scale": (0.99, "a fraction")}


def _check_eot(value: Any) -> dict[str, float]:
    eot = c.mapping("eot", value)
    out = {}
    with c.at("eot"):
        c.no_extra(eot, set(EOT_FIELDS))
        for key, raw in eot.items():
            most, unit = EOT_FIELDS[key]
            v = c.finite(key, raw)
            if not 0 <= v <= most:
                raise c.fail(key, raw, f"must be in [0, {most:g}] ({unit})")
            out[key] = v
    return out


HOLDOUT_EVERY = 4  # holdout "auto": every 4th frame (positions 3, 7, 11, ...) is held out


def _check_holdout(value: Any) -> None:
    valid = ('"auto" (every 4th frame), "none", {every: N, offset: K} or {frames: [positions]}')
    if value in ("auto", "none"):
        return
    if not isinstance(value, Mapping) or not value or set(value) - {"every", "offset", "frames"} \
            or ("frames" in value and len(value) != 1):
        raise c.fail("holdout", value, f"must be {valid}")
    if "frames" in value:
        frames = value["frames"]
        if isinstance(frames, (str, bytes)) or not isinstance(frames, list) or not frames:
            raise c.fail("holdout.frames", frames, "must be a non-empty list of frame positions")
        for i, f in enumerate(frames):
            c.integer(f"holdout.frames[{i}]", f, 0, 10**6)
        return
    c.integer("holdout.every", c.require(value, "every"), 2, 10**6)
    c.integer("holdout.offset", value.get("offset", 0), 0, 10**6)


@dataclass(frozen=True)
class Split:
    """A run's frame positions: ``attacked``, ``held_out`` (views held out within the attacked
    conditions) and ``held_out_conditions`` (every frame of a held-out condition). Unpacks as
    (attacked, every held-out position)."""

    attacked: list[int]
    held_out: list[int]
    held_out_conditions: list[int] = field(default_factory=list)

    @property
    def held(self) -> list[int]:
        return sorted(self.held_out + self.held_out_conditions)

    def __iter__(self) -> Any:
        return iter((self.attacked, self.held))


def split_conditions(holdout: Any, conditions: Any, held_conditions: Any = ()) -> Split:
    """The :class:`Split` of a sequence's ``(condition, positions)`` pairs
    (:meth:`undream.spec.Sequence.condition_ranges`; one pair for a sequence of one scene):
    :func:`split_frames` of ``holdout`` within each condition (positions counted from its first
    frame), and every frame of the conditions named in ``held_conditions``."""
    parts = list(conditions)
    names = [part.name for part, _ in parts]
    unknown = [h for h in held_conditions if h not in names]
    if unknown:
        raise c.fail("conditions.holdout", unknown, f"must name conditions of the run ({', '.join(names)})")
    out = Split([], [], [])
    for part, span in parts:
        if part.name in held_conditions:
            out.held_out_conditions.extend(span)
            continue
        try:
            attacked, held = split_frames(holdout, len(span))
        except SpecError as err:
            if len(parts) == 1:
                raise
            raise SpecError(f"condition {part.name!r}: {err}") from None
        out.attacked.extend(span.start + p for p in attacked)
        out.held_out.extend(span.start + p for p in held)
    if not out.attacked:
        raise c.fail("conditions.holdout", list(held_conditions), "holds out every condition; leave one to attack")
    return out


def split_frames(holdout: Any, n_frames: int) -> tuple[list[int], list[int]]:
    """(attacked, held-out) frame positions of a sequence of ``n_frames`` under ``holdout``.

    ``"auto"``: every 4th frame (positions 3, 7, ...) is held out when there are
    at least 4; ``"none"``: none; ``{every: N, offset: K}``: positions K, K + N, ...;
    ``{frames: [...]}``: those positions. Held-out frames are never rendered
    for a gradient; at least one frame must be left to attack.
    """
    _check_holdout(holdout)
    if holdout == "none" or (holdout == "auto" and n_frames < HOLDOUT_EVERY):
        return list(range(n_frames)), []
    if holdout == "auto":
        holdout = {"every": HOLDOUT_EVERY, "offset": HOLDOUT_EVERY - 1}
    if "frames" in holdout:
        bad = [f for f in holdout["frames"] if f >= n_frames]
        if bad:
            raise c.fail("holdout.frames", bad, f"must be positions below the sequence's {n_frames} frames")
        held = sorted(set(holdout["frames"]))
    else:
        held = list(range(holdout.get("offset", 0), n_frames, holdout["every"]))
    attacked = [f for f in range(n_frames) if f not in set(held)]
    if not attacked:
        raise c.fail("holdout", holdout, f"holds out all {n_frames} frames; leave at least one to attack")
    return attacked, held


def palettes_beside(data: Any, base_dir: str | Path) -> Any:
    """A run config mapping whose ``regularise`` block is read with its palette files relative to
    ``base_dir`` (the folder of the file that names them); anything else as it is."""
    if isinstance(data, Mapping) and isinstance(data.get("regularise"), Mapping):
        return {**data, "regularise": RegulariseConfig.from_json(data["regularise"], base_dir=base_dir)}
    return data


def profile_beside(data: Any, base_dir: str | Path) -> Any:
    """A run config mapping whose ``gamut``, when it is a profile's path, is made absolute against
    ``base_dir`` (the folder of the file that names it) and checked (readable, a CMYK printer's
    ICC profile: :func:`undream.spec.printing.check_profile`); anything else as it is."""
    value = data.get("gamut") if isinstance(data, Mapping) else None
    if not isinstance(value, str) or value in ("default", "none"):
        return data
    profile = Path(check_gamut(value)).expanduser()
    profile = profile if profile.is_absolute() else Path(base_dir) / profile
    return {**data, "gamut": str(check_profile(profile).resolve())}


def load_run_config(path: str | Path) -> RunConfig:
    """Parse ``RUN.yaml``; errors name the file and the field."""
    path = Path(path)
    data = read_yaml(path)
    try:
        config = RunConfig.from_json(profile_beside(palettes_beside(data, path.parent), path.parent))
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None
    named = [("scene", config.scene)] + [(f"conditions.scenes[{i}]", s) for i, s in
                                         enumerate(config.conditions.scenes if config.conditions else ())]
    for field_name, value in named:
        scene = Path(value) if Path(value).is_absolute() else path.parent / value
        if not ((scene / "sequence.json").is_file() or scene.is_file()):
            raise SpecError(f"{path}: {field_name}: {scene} is neither a scene directory nor a spec file")
    return config
