"""Datasets for the bundled victims: undream's own renders of the built-in assets.

Each image shows ONE built-in object (class = its name, uniform over
:data:`CLASSES`) with a random texture, at a random yaw, on a random
background under a random environment, seen by a random camera. It is
rendered by the project's own scene adapter
(:func:`undream.scene.mitsuba_scene.scene_dict`, ``sim`` view, path traced,
``volpath`` in fog) and its box comes from the ``mask`` view (the object's
visible pixels behind every occluder).

Three distributions (:attr:`DatasetConfig.distribution`): ``v1``, below, the
data of ``bundled:classifier`` / ``bundled:detector`` (a camera orbiting the
object at a random elevation, three backgrounds, four weathers), ``v2``
(:mod:`undream.training.distribution_v2`), the data of the ``-v2`` victims
(camera height and ground distance, every background and weather), and
``v3`` (:mod:`undream.training.distribution_v3`), the data of the ``-v3``
victims (``v2`` with plain, unsaturated objects too). The rest of this
docstring describes ``v1``; ``v2`` and ``v3`` follow the same rules with
their own parameters.

Held-out split: ``train`` and ``test`` draw the environment and the camera
from DISJOINT parameter sets. Every banded parameter (:data:`BANDS`) is cut
into an odd number of equal bands that alternate between the splits (even
bands: train, odd bands: test), so each test band lies between two training
bands (the held-out set interpolates, it never extrapolates). No test image
shares a time of day, fog density, camera azimuth, elevation, field of view
or object size in the frame with any training image. Weather, background and
texture kinds occur in both.

Output of :func:`make_dataset` (sRGB PNGs, 8 bit)::

    OUT/images/00000.png ...
    OUT/labels.jsonl      one JSON object per image (see :func:`render_sample`)
    OUT/metadata.json     the config, classes, split rules, variant, versions, command
    OUT/shading/00000.npz ...  with ``shading``: each image's shading (:func:`render_shading`)

Reproducible: sample ``i`` of ``(seed, split)`` depends on those three only
(its generator is ``default_rng([seed, split_id, i])``), so a dataset can be
regenerated or extended bit for bit on the same machine.
"""
from __future__ import annotations

import contextlib
import json
import math
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Iterable, Iterator

import numpy as np
from PIL import Image

from undream.color import linear_to_srgb, srgb_to_linear, to_uint8
from undream.errors import DatasetError
from undream.progress import progress as progress_bar
from undream.scene.builtin import builtin_mesh
from undream.scene.mesh import write_ply
from undream.scene.mitsuba_scene import OBJECT_ID, ScenePaths, scene_dict
from undream.scene.poses import look_at, object_pose, yaw_rotation
from undream.scene.xml import to_mitsuba
from undream.scenedir.verify import mask_box
from undream.spec.io import check_new_folder, restored_on_failure
from undream.spec import Asset, Camera, Environment, Frame, Sequence, TextureParam, Transform
from undream.training import distribution_v2 as v2
from undream.training import distribution_v3 as v3
from undream.training import bands as banding
from undream.training.bands import SPLITS
from undream.training.textures import (PLAIN_SATURATION, PLAIN_SHARE, PLAIN_VALUE, TEXTURE_KINDS, make_texture,
                                       texture_recipe)
from undream.variant import mitsuba
from undream.versions import versions

# The bundled victims' classes: the built-in assets they were trained on (fixed, so that a new
# built-in asset, such as the pedestrian actor, changes neither the data set nor the victims).
CLASSES: tuple[str, ...] = ("car", "sphere", "stop_sign", "traffic_cone", "trash_bin", "umbrella")
DATASET_VERSION = 1
LABELS_FILE = "labels.jsonl"
METADATA_FILE = "metadata.json"
SHADING_DIR = "shading"

# Banded parameters: (low, high, band width); band k = floor((v - low) / width) belongs to
# train when k is even, to test when k is odd.
BANDS: dict[str, tuple[float, float, float]] = {
    "azimuth_deg": (0.0, 360.0, 30.0),  # camera around the object, 0 = in front of it (cyclic)
    "elevation_deg": (2.0, 44.0, 6.0),  # camera above the object's centre
    "fov_deg": (30.0, 60.0, 6.0),  # horizontal field of view
    "coverage": (0.35, 0.85, 0.1),  # bounding-sphere diameter / frame width
    "fog_density": (0.01, 0.06, 0.01),  # 1/m (used in fog only)
    "day_time_h": (7.5, 16.5, 1.0),  # time_of_day, weathers other than night
    "night_time_h": (20.0, 29.0, 1.0),  # time_of_day at night; hours after midnight count from 24
}
WEATHER_WEIGHTS = {"clear": 0.35, "cloudy": 0.25, "night": 0.2, "fog": 0.2}
# The backgrounds the bundled victims were trained on (newer ones, e.g. city, stay unseen: held-out scenery,
# and the data sets stay reproducible bit for bit).
TRAINING_BACKGROUNDS = ("plain", "park", "street")
DISTRIBUTIONS = ("v1", v2.NAME, v3.NAME)
# The camera parameters whose test bands the evaluation reports one by one, per distribution.
CAMERA_BANDS = {"v1": ("elevation_deg", "coverage"), v2.NAME: v2.REPORTED_BANDS, v3.NAME: v3.REPORTED_BANDS}
MIN_VISIBLE_PIXELS = 60  # pixels at least half covered by the object
BOX_COVERAGE = 0.1  # a pixel joins the box when the object covers more than this share of it
MAX_TRIES = 20
RENDER_VARIANT = "scalar_rgb"  # no JIT: each small scene renders without compiling kernels


@dataclass(frozen=True)
class DatasetConfig:
    """What :func:`make_dataset` renders: ``n`` images of ``split`` from ``seed``.

    size: image width = height in pixels; spp: samples per pixel of the image
    (the mask uses the same count); shading: also render and save each
    image's texture-free shading (:func:`render_shading`, ``shading/NNNNN.npz``),
    which :mod:`undream.training.adversarial` composites attacked textures with;
    distribution: ``v1`` (this module's
    orbiting camera, the original bundled victims' data, kept bit for bit),
    ``v2`` (:mod:`undream.training.distribution_v2`: camera height and ground
    distance, every background and weather, kept bit for bit) or ``v3``
    (:mod:`undream.training.distribution_v3`: ``v2`` with plain textures too).
    """

    n: int
    seed: int
    split: str = "train"
    size: int = 64
    spp: int = 16
    distribution: str = "v1"
    shading: bool = False  # also write each image's shading (:func:`render_shading`): attackable in training

    def __post_init__(self) -> None:
        if self.distribution not in DISTRIBUTIONS:
            raise DatasetError(f"distribution: must be one of {', '.join(DISTRIBUTIONS)}, "
                               f"got {self.distribution!r}")
        if self.split not in SPLITS:
            raise DatasetError(f"split: must be one of {', '.join(SPLITS)}, got {self.split!r}")
        for name, lo in (("n", 1), ("size", 16), ("spp", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise DatasetError(f"{name}: must be an integer >= {lo}, got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2**32:
            raise DatasetError(f"seed: must be an integer in [0, 2^32), got {self.seed!r}")


@dataclass(frozen=True)
class SampleParams:
    """Everything random about one image (angles in degrees, lengths in metres)."""

    label: int
    yaw_deg: float  # object yaw in the world
    azimuth_deg: float  # camera azimuth relative to the object's front (+Z), in [0, 360)
    elevation_deg: float
    fov_deg: float
    coverage: float
    shift: tuple[float, float]  # look-at offset, fractions of the half frame (x, y)
    environment: Environment
    texture: dict[str, Any] = field(default_factory=dict)  # kind and its parameters

    @property
    def name(self) -> str:
        return CLASSES[self.label]


# --------------------------------------------------------------------------- the split

def band_index(param: str, value: float) -> int:
    """The band of ``value`` for the ``v1`` banded parameter ``param`` (see :data:`BANDS`)."""
    return banding.band_index(BANDS, param, value)


def distribution_of(params: dict[str, Any]) -> str:
    """The camera model (``v1`` or ``v2``) that drew a label record's ``params``: a ``v3``
    record, whose camera and bands are ``v2``'s, reads as ``v2``."""
    return v2.NAME if "height_m" in params else "v1"


def bands_of(distribution: str) -> banding.Bands:
    """The band table of a distribution (:data:`BANDS`, or :data:`~.distribution_v2.BANDS_V2`
    for ``v2`` and ``v3``)."""
    return v2.BANDS_V2 if distribution in (v2.NAME, v3.NAME) else BANDS


def banded_values(params: dict[str, Any]) -> dict[str, float]:
    """The banded values of one image's parameters (a label record's ``params``), of
    :data:`BANDS` or, for a ``v2`` record, :data:`~.distribution_v2.BANDS_V2`."""
    if distribution_of(params) == v2.NAME:
        return v2.banded_values(params)
    return banding.record_values(params, ("azimuth_deg", "elevation_deg", "fov_deg", "coverage"))


def splits_of(params: dict[str, Any]) -> set[str]:
    """The splits that the banded values of ``params`` belong to (one for a valid image)."""
    bands = bands_of(distribution_of(params))
    return {banding.split_of(bands, k, v) for k, v in banded_values(params).items()}


def _banded(rng: np.random.Generator, param: str, split: str) -> float:
    return banding.draw_banded(rng, BANDS, param, split)


def _time_of_day(rng: np.random.Generator, weather: str, split: str) -> float:
    if weather == "night":
        return _banded(rng, "night_time_h", split) % 24.0
    return _banded(rng, "day_time_h", split)


def sample_params(rng: np.random.Generator, split: str, label: int | None = None) -> SampleParams:
    """Draw one image's parameters for ``split`` (see the module docstring); the
    class is ``label`` when given, else drawn uniformly."""
    if split not in SPLITS:
        raise DatasetError(f"split: must be one of {', '.join(SPLITS)}, got {split!r}")
    if label is None:
        label = int(rng.integers(len(CLASSES)))
    weather = str(rng.choice(list(WEATHER_WEIGHTS), p=list(WEATHER_WEIGHTS.values())))
    env = Environment(weather=weather, time_of_day=_time_of_day(rng, weather, split),
                      background=str(rng.choice(TRAINING_BACKGROUNDS)),
                      sun_max_elevation_deg=float(rng.uniform(35.0, 75.0)),
                      fog_density=_banded(rng, "fog_density", split))
    coverage = _banded(rng, "coverage", split)
    room = 1.0 - coverage  # keeps the bounding sphere about inside the frame
    return SampleParams(
        label=label, yaw_deg=float(rng.uniform(0.0, 360.0)),
        azimuth_deg=_banded(rng, "azimuth_deg", split),
        elevation_deg=_banded(rng, "elevation_deg", split),
        fov_deg=_banded(rng, "fov_deg", split), coverage=coverage,
        shift=(float(rng.uniform(-room, room)), float(rng.uniform(-room, room))),
        environment=env, texture=texture_recipe(rng))


# --------------------------------------------------------------------------- scenes

def _object_sphere(name: str) -> tuple[np.ndarray, float]:
    """Centre (object frame, metres) and radius of the mesh's bounding-box sphere."""
    lo, hi = builtin_mesh(name).bounds()
    return (lo + hi) / 2.0, float(np.linalg.norm(hi - lo)) / 2.0


class _Meshes:
    """The built-in meshes written once as PLY files, and their bounding spheres."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.spheres: dict[str, tuple[np.ndarray, float]] = {}
        for name in CLASSES:
            (root / name / "meshes").mkdir(parents=True, exist_ok=True)
            write_ply(builtin_mesh(name), ScenePaths(str(root / name)).mesh(OBJECT_ID))
            self.spheres[name] = _object_sphere(name)

    def paths(self, name: str) -> ScenePaths:
        return ScenePaths(str(self.root / name))


def sample_frame(p: SampleParams, sphere: tuple[np.ndarray, float], size: int, seed: int) -> Sequence:
    """A one-frame :class:`Sequence` of the sample (object at the origin, yawed)."""
    centre_obj, radius = sphere
    rot = yaw_rotation(p.yaw_deg)
    obj = object_pose((0.0, 0.0, 0.0), rot)
    centre = rot.apply(centre_obj)
    half = math.radians(p.fov_deg) / 2.0
    dist = radius / math.sin(p.coverage * half)
    az, el = math.radians(p.yaw_deg + p.azimuth_deg), math.radians(p.elevation_deg)
    eye = centre + dist * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    base = look_at(eye, centre)
    # move the look-at point so the object sits off-centre by `shift` (fractions of the half frame)
    span = dist * math.tan(half)
    target = centre + span * (p.shift[0] * base[:3, 0] + p.shift[1] * base[:3, 1])
    cam = Camera(Transform.from_rows(look_at(eye, target)), p.fov_deg, (size, size))
    env = p.environment
    frame = Frame(index=0, camera=cam, object_to_world=Transform.from_rows(obj), environment=env)
    asset = Asset(name="object", mesh=f"builtin:{p.name}",
                  texture=TextureParam(resolution=(size, size)))
    return Sequence(name="sample", asset=asset, frames=(frame,), seed=seed)


def _scene(mi: ModuleType, seq: Sequence, paths: ScenePaths, kind: str, spp: int,
           texture_srgb: np.ndarray | None) -> Any:
    d = to_mitsuba(scene_dict(seq, seq.frames[0], paths, kind), mi, {"spp": spp})
    if texture_srgb is not None:
        d[OBJECT_ID]["bsdf"]["bsdf"]["reflectance"] = {
            "type": "bitmap", "data": mi.TensorXf(srgb_to_linear(texture_srgb)), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "repeat"}
    return mi.load_dict(d)


def render_shading(mi: ModuleType, seq: Sequence, paths: ScenePaths, spp: int, index: int,
                   coverage: np.ndarray) -> dict[str, np.ndarray]:
    """What an image looks like under ANY texture, as arrays (float32): the linear radiance with a black
    (``black``) and a white (``white``) texture, the object's texture coordinates (``uv``, H×W×2: the
    mean over the pixel's samples that hit the object, rendered with the object alone) and the share
    of the pixel the object visibly covers (``coverage``, H×W, the ``mask`` view's).

    The object is diffuse: a camera sample that first hits it carries ``albedo(uv) · L_white`` plus
    what does not depend on its albedo (fog in front of it), so a texture ``t`` (linear) renders
    about as ``black + (white − black) · t(uv)`` (exactly so up to the light the object throws back
    onto itself and onto its surroundings, and the pixels a texture seam crosses)."""
    def render(value: float) -> np.ndarray:  # the object in one colour, its texture every texel `value`
        scene = _scene(mi, seq, paths, "sim", spp, np.full((2, 2, 3), value, np.float32))
        return np.array(mi.render(scene, seed=index), dtype=np.float32)[..., :3]

    black, white = render(0.0), render(1.0)
    # The object alone (an emitter of radiance 1 in the mask view, nothing in front of it): its
    # unoccluded coverage and the sum of its uv over the samples that hit it (misses add 0).
    d = to_mitsuba(scene_dict(seq, seq.frames[0], paths, "mask"), mi, {"spp": spp})
    d = {"type": "scene", "sensor": d["sensor"], OBJECT_ID: d[OBJECT_ID],
         "integrator": {"type": "aov", "aovs": "uv:uv", "image": d["integrator"]}}
    out = np.array(mi.render(mi.load_dict(d), seed=index), dtype=np.float32)
    alone, uv_sum = out[..., 0], out[..., -2:]
    uv = np.where(alone[..., None] > 1e-3, uv_sum / np.maximum(alone[..., None], 1e-3), 0.0)
    return {"black": black, "white": white, "uv": uv.astype(np.float32), "coverage": coverage.astype(np.float32)}


def render_sample(mi: ModuleType, meshes: _Meshes, cfg: DatasetConfig, index: int
                  ) -> tuple[np.ndarray, dict[str, Any]]:
    """Render sample ``index``: the H×W×3 uint8 sRGB image and its label record (with
    ``cfg.shading``, the record's ``shading`` holds :func:`render_shading`'s arrays).

    The record holds ``label``, ``name``, ``box`` (xyxy pixels: every pixel
    the object visibly covers by more than :data:`BOX_COVERAGE`, so thin
    poles count whenever they show), ``visible_pixels`` (pixels covered by
    more than half), the drawn parameters (``params``), the
    camera's ``to_world`` and the environment. The class is drawn once; the
    rest is redrawn (up to :data:`MAX_TRIES` times) while the object shows
    fewer than :data:`MIN_VISIBLE_PIXELS` pixels (``v2``: the same share of the
    frame, :func:`~.distribution_v2.min_visible_pixels`; ``v3`` likewise), so classes stay uniform.
    """
    rng = np.random.default_rng([cfg.seed, SPLITS.index(cfg.split), index])
    label = int(rng.integers(len(CLASSES)))
    sphere = meshes.spheres[CLASSES[label]]
    street = {v2.NAME: v2, v3.NAME: v3}.get(cfg.distribution)  # the camera placed on the ground plan
    # v1: 60 pixels, or the same share of a smaller image (60 of 256 pixels at --size 16 was never met)
    min_visible = min(MIN_VISIBLE_PIXELS, v2.min_visible_pixels(cfg.size)) if street is None \
        else v2.min_visible_pixels(cfg.size)
    for attempt in range(MAX_TRIES):
        p: SampleParams | v2.SampleParamsV2
        if street is not None:
            p = street.sample_params(rng, cfg.split, label, CLASSES[label], sphere)
            seq = street.sample_frame(p, sphere, cfg.size, seed=int(rng.integers(2**31)))
        else:
            p = sample_params(rng, cfg.split, label)
            seq = sample_frame(p, sphere, cfg.size, seed=int(rng.integers(2**31)))
        paths = meshes.paths(p.name)
        mask_img = np.array(mi.render(_scene(mi, seq, paths, "mask", cfg.spp, None), seed=index))
        coverage = mask_img.mean(axis=2)
        mask, box = coverage > 0.5, mask_box(coverage > BOX_COVERAGE)
        if box is not None and int(mask.sum()) >= min_visible:
            break
    else:
        raise DatasetError(f"sample {index}: in {MAX_TRIES} draws the object never covered {min_visible} of the "
                           f"{cfg.size}×{cfg.size} pixels (--size {cfg.size}, --distribution {cfg.distribution}); "
                           "a larger --size shows it bigger")
    texture = make_texture(p.texture, cfg.size)
    lin = np.array(mi.render(_scene(mi, seq, paths, "sim", cfg.spp, texture), seed=index))
    image = to_uint8(linear_to_srgb(lin))
    params = asdict(p)
    params["environment"] = p.environment.to_json()
    record = {"file": f"images/{index:05d}.png", "index": index, "label": p.label, "name": p.name,
              "box": list(box), "visible_pixels": int(mask.sum()), "redraws": attempt,
              "params": params, "camera_to_world": seq.frames[0].camera.to_world.to_json()}
    if cfg.shading:
        record["shading"] = render_shading(mi, seq, paths, cfg.spp, index, coverage)
    return image, record


# --------------------------------------------------------------------------- datasets

@contextlib.contextmanager
def _mitsuba_variant(name: str) -> Iterator[ModuleType]:
    """Mitsuba with variant ``name`` for the block; the process's own variant (the
    one :func:`undream.variant.mitsuba` picks) is set again after it."""
    before = mitsuba().variant()
    mi = mitsuba(name)
    try:
        yield mi
    finally:
        if mi.variant() != before:
            mi.set_variant(before)


def make_dataset(out: str | Path, cfg: DatasetConfig, progress: bool = True,
                 variant: str = RENDER_VARIANT, command: str = "") -> Path:
    """Render ``cfg.n`` images into ``out`` (see the module docstring); returns ``out``.

    ``variant`` is the Mitsuba variant to render with: by default the scalar
    CPU one, several times faster than the JIT variants for many small,
    differently shaped scenes (each would compile its own kernels); the
    process's variant is restored afterwards. Refuses a folder that already
    holds a dataset. ``command`` (the command line that asked) goes into the
    metadata.
    """
    out = Path(out)
    if (out / LABELS_FILE).exists():
        raise DatasetError(f"{out}: already holds a dataset ({LABELS_FILE}); choose another folder")
    check_new_folder(out)
    partial = out / (LABELS_FILE + ".partial")  # renamed when complete
    with restored_on_failure(out):  # Ctrl-C, SIGTERM, a full disk: the folder goes back to how it was found
        (out / "images").mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="undream-meshes-") as tmp, \
                _mitsuba_variant(variant) as mi, open(partial, "w", encoding="utf-8") as fh:
            meshes = _Meshes(Path(tmp))
            for i in progress_bar(range(cfg.n), f"render {cfg.split}", "image", progress):
                image, rec = render_sample(mi, meshes, cfg, i)
                Image.fromarray(image).save(out / rec["file"])
                if cfg.shading:
                    rec["shading"] = _save_shading(out, i, rec.pop("shading"))
                fh.write(json.dumps(rec) + "\n")
    partial.replace(out / LABELS_FILE)
    v2_data = cfg.distribution in (v2.NAME, v3.NAME)
    meta = {"version": DATASET_VERSION, "config": asdict(cfg), "distribution": cfg.distribution,
            "classes": list(CLASSES), "bands": {k: list(v) for k, v in bands_of(cfg.distribution).items()},
            "band_rule": "band k = floor((value - low) / width); even k: train, odd k: test",
            "weather_weights": v2.WEATHER_WEIGHTS_V2 if v2_data else WEATHER_WEIGHTS,
            "backgrounds": list(v2.BACKGROUNDS if v2_data else TRAINING_BACKGROUNDS),
            **({"coverage": list(v2.COVERAGE)} if v2_data else {}),
            **({"plain_textures": _plain_textures()} if cfg.distribution == v3.NAME else {}),
            "mitsuba_variant": variant,
            "versions": versions(), "command": command}
    (out / METADATA_FILE).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    return out


def _save_shading(out: Path, index: int, arrays: dict[str, np.ndarray]) -> str:
    """Write an image's shading (float16: radiance and coverage in [0, 65504], uv to 2⁻¹¹) and return its
    file, relative to ``out``."""
    rel = f"{SHADING_DIR}/{index:05d}.npz"
    (out / SHADING_DIR).mkdir(exist_ok=True)
    np.savez_compressed(out / rel, **{k: v.astype(np.float16) for k, v in arrays.items()})
    return rel


def _plain_textures() -> dict[str, Any]:
    """The ``v3`` plain textures' share and ranges, for the metadata."""
    return {"share": PLAIN_SHARE, "hsv_saturation": list(PLAIN_SATURATION), "hsv_value_srgb": list(PLAIN_VALUE)}


@dataclass(frozen=True)
class Dataset:
    """A dataset in memory: ``images`` N×H×W×3 uint8 sRGB, ``labels`` N (int64),
    ``boxes`` N×4 xyxy pixels (float32), the label ``records`` and ``metadata``."""

    images: np.ndarray
    labels: np.ndarray
    boxes: np.ndarray
    records: list[dict[str, Any]]
    metadata: dict[str, Any]

    def __len__(self) -> int:
        return len(self.labels)


def read_records(folder: str | Path) -> Iterator[dict[str, Any]]:
    path = Path(folder) / LABELS_FILE
    if not path.is_file():
        raise DatasetError(f"{folder}: not a dataset (no {LABELS_FILE}); make one with "
                           f"'undream victims make-dataset'")
    with open(path, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            try:
                yield json.loads(line)
            except json.JSONDecodeError as err:
                raise DatasetError(f"{path}: line {n} is not JSON ({err.msg})") from None


def load_dataset(folder: str | Path) -> Dataset:
    """Read a folder written by :func:`make_dataset`."""
    folder = Path(folder)
    records = list(read_records(folder))
    meta_path = folder / METADATA_FILE
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
    if meta.get("classes", list(CLASSES)) != list(CLASSES):
        raise DatasetError(f"{folder}: classes {meta.get('classes')} differ from {list(CLASSES)}")
    images = []
    for rec in records:
        try:
            images.append(np.asarray(Image.open(folder / rec["file"]).convert("RGB")))
        except (OSError, KeyError) as err:
            raise DatasetError(f"{folder}: cannot read image of record {rec.get('index')} ({err})") from None
    if not records:
        raise DatasetError(f"{folder}: {LABELS_FILE} is empty")
    return Dataset(np.stack(images), np.array([r["label"] for r in records], dtype=np.int64),
                   np.array([r["box"] for r in records], dtype=np.float32), records, meta)


def load_datasets(folders: Iterable[str | Path]) -> Dataset:
    """Several folders written by :func:`make_dataset` as one training set, in the order given.

    They must be parts of one set: the same distribution, split, image size and samples per
    pixel. Each image of a dataset depends only on its ``(seed, split, index)``, so two parts
    drawn under one seed would repeat images: a seed given twice is refused, as is a folder given
    twice. The result's ``metadata`` is the first part's, with ``parts``: every part's config,
    folder and command.
    """
    folders = [Path(f) for f in folders]
    if not folders:
        raise DatasetError("no dataset given")
    if len(folders) == 1:
        return load_dataset(folders[0])
    resolved = [f.resolve() for f in folders]
    for k, f in enumerate(resolved):
        if f in resolved[:k]:
            raise DatasetError(f"{folders[k]}: given twice")
    parts = [load_dataset(f) for f in folders]
    first = parts[0].metadata.get("config") or {}
    seeds: dict[Any, Path] = {}
    for folder, ds in zip(folders, parts):
        cfg = ds.metadata.get("config")
        if not cfg:
            raise DatasetError(f"{folder}: no config in its {METADATA_FILE}; cannot tell whether it is "
                               "a part of the same set")
        for key in ("distribution", "split", "size", "spp"):
            if cfg.get(key) != first.get(key):
                raise DatasetError(f"{folder}: {key} {cfg.get(key)!r} differs from {folders[0]}'s "
                                   f"{first.get(key)!r}; the parts of one training set must agree")
        if cfg.get("seed") in seeds:
            raise DatasetError(f"{folder}: seed {cfg.get('seed')} is {seeds[cfg.get('seed')]}'s too, and "
                               "the same seed draws the same images; make the other part with another --seed")
        seeds[cfg.get("seed")] = folder
    meta = {**parts[0].metadata,
            "parts": [{"folder": str(f), "n": len(ds), "config": ds.metadata.get("config"),
                       "command": ds.metadata.get("command")} for f, ds in zip(folders, parts)]}
    return Dataset(np.concatenate([ds.images for ds in parts]), np.concatenate([ds.labels for ds in parts]),
                   np.concatenate([ds.boxes for ds in parts]), [r for ds in parts for r in ds.records], meta)
