"""The Unreal export importer, the editor-side export script (without Unreal) and the fixture."""
from __future__ import annotations

import json
import math
import sys
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from undream.bridge import unreal_import
from undream.bridge.unreal_import import sequence_from_unreal
from undream.errors import BridgeError
from undream.spec import Sequence

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "examples" / "unreal" / "drive_by_export.json"
sys.path.insert(0, str(ROOT / "tests" / "fixtures"))
import make_unreal_fixture  # noqa: E402

BIN_RADIUS_M, BIN_HEIGHT_M = 0.31, 1.0  # builtin:trash_bin, Ø0.62 m × 1.0 m, standing on y = 0


def project(cam: Any, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical world points (N, 3) → pixel (x right, y down) and depth, Mitsuba's camera model."""
    m = np.array(cam.to_world.matrix)
    local = (np.linalg.inv(m) @ np.c_[points, np.ones(len(points))].T).T[:, :3]
    fw, fh = cam.film_size
    ox, oy = cam.crop_offset
    f = fw / (2 * math.tan(math.radians(cam.fov_deg) / 2))  # pixels per unit of the tan plane
    x = fw / 2 - f * local[:, 0] / local[:, 2] - ox  # local +X is the image's left
    y = fh / 2 - f * local[:, 1] / local[:, 2] - oy
    return np.c_[x, y], local[:, 2]


def bin_points(frame: Any) -> np.ndarray:
    th = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = np.c_[BIN_RADIUS_M * np.sin(th), np.zeros_like(th), BIN_RADIUS_M * np.cos(th)]
    local = np.r_[ring, ring + [0, BIN_HEIGHT_M, 0]]
    m = np.array(frame.object_to_world.matrix)
    return (m @ np.c_[local, np.ones(len(local))].T).T[:, :3]


def fixture_data() -> dict[str, Any]:
    return json.loads(FIXTURE.read_text())


def write(tmp_path: Path, data: Any, name: str = "drive_by.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


# --- the fixture ------------------------------------------------------------------

def test_fixture_imports_as_a_plausible_shot():
    seq = sequence_from_unreal(FIXTURE)
    assert isinstance(seq, Sequence) and seq.source == "unreal" and seq.name == "DriveBy"
    assert [f.index for f in seq.frames] == list(range(8))
    assert seq.fps == 10.0 and seq.frames[3].time == pytest.approx(0.3)
    assert seq.asset.builtin == "trash_bin" and [a.name for a in seq.actors] == ["car1"]
    for frame in seq.frames:
        cam = frame.camera
        assert cam.to_world.is_rigid() and cam.resolution == (64, 36) and cam.film == (64, 42)
        assert cam.to_world.translation == pytest.approx((0.0, 1.6, 0.0))
        px, depth = project(cam, bin_points(frame))
        assert np.all((6.0 < depth) & (depth < 10.0))  # the bin is 6–10 m ahead
        width = (px[:, 0].max() - px[:, 0].min()) / 64
        assert 0.10 < width < 0.40  # clearly visible
        assert np.all((px >= 0) & (px <= [64, 36]))  # wholly in the image
        centre = px.mean(axis=0)
        assert 24 < centre[0] < 40 and abs(centre[0] - 32) > 0.3  # near the centre, not on it
        car_px, car_depth = project(cam, np.array([frame.actors[0].to_world.translation]))
        assert car_depth[0] > 15.0  # behind the bin


def test_fixture_car_drives_by_behind_the_bin():
    seq = sequence_from_unreal(FIXTURE)
    xs = [project(f.camera, np.array([f.actors[0].to_world.translation]))[0][0, 0] for f in seq.frames]
    assert np.all(np.diff(xs) > 0)  # left to right across the image
    bin_x = project(seq.frames[4].camera, np.array([seq.frames[4].object_to_world.translation]))[0][0, 0]
    assert xs[0] < bin_x < xs[-1]


def test_fixture_is_up_to_date():
    assert make_unreal_fixture.build() == fixture_data(), "run tests/fixtures/make_unreal_fixture.py"


# --- ordering and conventions --------------------------------------------------------

def test_frames_are_ordered_numerically(tmp_path):
    data = fixture_data()
    frames = data["frames"][:4]
    for f, number in zip(frames, ["10", "9", "0011", 100]):
        f["frame"] = number
    data["frames"] = frames
    seq = sequence_from_unreal(write(tmp_path, data))
    assert [f.index for f in seq.frames] == [9, 10, 11, 100]
    # index 9 is the export's second entry: its camera yaw
    yaw_9 = sequence_from_unreal(write(tmp_path, {**data, "frames": [frames[1]]})).frames[0]
    assert seq.frames[0].camera == yaw_9.camera
    assert seq.frames[0].time == frames[1]["time"]


def test_time_defaults_to_frame_over_fps(tmp_path):
    data = fixture_data()
    for f in data["frames"]:
        del f["time"]
    data["frames"][5]["frame"] = 25
    seq = sequence_from_unreal(write(tmp_path, data))
    assert seq.frames[-1].index == 25 and seq.frames[-1].time == pytest.approx(2.5)


def test_environment_per_frame_is_merged_over_the_top_level(tmp_path):
    data = fixture_data()
    data["frames"][3]["environment"] = {"weather": "fog"}
    seq = sequence_from_unreal(write(tmp_path, data))
    assert seq.frames[3].environment.weather == "fog"
    assert seq.frames[3].environment.time_of_day == 15.5
    assert seq.frames[2].environment.weather == "clear"


def test_relative_paths_resolve_against_the_export(tmp_path):
    data = fixture_data()
    data["object"]["asset"]["mesh"] = "meshes/bin.obj"
    data["object"]["asset"]["texture"]["init"] = "../start.png"
    data["actors"][0]["asset"]["mesh"] = str(tmp_path / "car.ply")
    (tmp_path / "sub").mkdir()
    seq = sequence_from_unreal(write(tmp_path / "sub", data))
    assert seq.asset.mesh == str((tmp_path / "sub" / "meshes" / "bin.obj").resolve())
    assert seq.texture.init == str((tmp_path / "start.png").resolve())
    assert seq.actors[0].mesh == str(tmp_path / "car.ply")


def test_name_comes_from_the_sequence_path_or_the_name_field(tmp_path):
    data = fixture_data()
    data["sequence"] = "/Game/Shots/Shot 010.Shot 010"
    assert sequence_from_unreal(write(tmp_path, data)).name == "Shot_010"
    data["name"] = "my-shot"
    assert sequence_from_unreal(write(tmp_path, data)).name == "my-shot"


def test_object_without_texture_gets_the_default(tmp_path):
    data = fixture_data()
    del data["object"]["asset"]["texture"]
    assert sequence_from_unreal(write(tmp_path, data)).texture.resolution == (256, 256)


# --- malformed exports ------------------------------------------------------------------

def _set(path: list[Any], value: Any):
    def mutate(d: dict[str, Any]) -> None:
        for key in path[:-1]:
            d = d[key]
        if value is _DELETE:
            del d[path[-1]]
        else:
            d[path[-1]] = value
    return mutate


_DELETE = object()
F = "frames"

MALFORMED = [
    (_set([F, 3, "camera", "fov"], _DELETE), "frames[3].camera.fov: is required"),
    (_set([F, 3, "camera", "rotation", 1], float("nan")), "frames[3].camera.rotation[1]: must be finite, got nan"),
    (_set([F, 2, "transforms", "Car1", "location", 0], float("inf")),
     "frames[2].transforms.Car1.location[0]: must be finite, got inf"),
    (_set([F, 1, "transforms", "AdvBin", "scale", 2], 0.0), "frames[1].transforms.AdvBin.scale[2]: must be non-zero"),
    (_set([F, 2, "transforms", "AdvBin"], _DELETE), "frames[2].transforms: missing actor 'AdvBin'"),
    (_set([F, 1, "transforms", "Ghost"], {"location": [0, 0, 0], "rotation": [0, 0, 0]}),
     "frames[1].transforms: unknown actor 'Ghost' (declared: AdvBin, Car1)"),
    (_set([F, 4, "frame"], 2), "frames[4].frame: duplicate frame number 2 (also frames[2])"),
    (_set([F, 0, "frame"], "ten"), "frames[0].frame: must be a frame number"),
    (_set([F, 0, "frame"], -3), "frames[0].frame: must be a frame number"),
    (_set([F, 0, "camera", "fov"], 180), "frames[0].camera.fov: must be the horizontal field of view"),
    (_set([F, 0, "camera", "filmback", 1], 0), "frames[0].camera.filmback[1]: must be > 0"),
    (_set([F, 0, "camera", "resolution"], [64.0, 36]), "frames[0].camera.resolution[0]: must be an integer"),
    (_set([F, 0, "camera", "location"], [1, 2]), "frames[0].camera.location: must be a list of 3 numbers"),
    (_set([F, 0, "camera", "zoom"], 2), "frames[0].camera.zoom: unknown field"),
    (_set([F, 5, "environment"], {"time_of_day": 25}), "frames[5].environment.time_of_day: must be hours"),
    (_set([F], []), "frames: must be a non-empty list"),
    (_set(["format"], "unreal-export"), "format: must be 'undream-unreal-export', got 'unreal-export'"),
    (_set(["version"], 2), "version: must be 1, got 2"),
    (_set(["fps"], 0), "fps: must be > 0, got 0"),
    (_set(["colour"], "red"), "colour: unknown field"),
    (_set(["object", "actor"], _DELETE), "object.actor: is required"),
    (_set(["object", "asset", "texture", "resolution"], [0, 5]), "object.asset.texture.resolution[0]: must be"),
    (_set(["object", "asset", "mesh"], "bin.fbx"), "object.asset.mesh: must be 'builtin:NAME'"),
    (_set(["actors", 0, "asset", "mesh"], _DELETE), "actors[0].asset.mesh: is required"),
    (lambda d: d["actors"].append({"actor": "Car1", "asset": {"name": "car2", "mesh": "builtin:car"}}),
     "actors[1].actor: must name each actor once"),
    (_set(["actors", 0, "asset", "name"], "bin"), "actors[0].asset.name: must be unique"),
    (_set(["environment", "weather"], "hail"), "environment.weather: must be one of"),
]


@pytest.mark.parametrize("mutate, message", MALFORMED, ids=[m for _, m in MALFORMED])
def test_malformed_export_names_file_and_field(tmp_path, mutate, message):
    data = fixture_data()
    mutate(data)
    path = write(tmp_path, data)
    with pytest.raises(BridgeError) as err:
        sequence_from_unreal(path)
    text = str(err.value)
    assert text.startswith(f"{path}: ") and message in text, text
    assert "\n" not in text


@pytest.mark.parametrize("text, message", [
    ('{"format": "undream-unreal-export",\n "version": 1,,\n}', "line 2 column 15: not valid JSON"),
    ("[1, 2]", "export: must be a JSON object"),
    ("", "line 1 column 1: not valid JSON"),
])
def test_unreadable_export(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(BridgeError) as err:
        sequence_from_unreal(path)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(BridgeError, match="file not found"):
        sequence_from_unreal(tmp_path / "nope.json")


# --- the editor-side export script, without Unreal ----------------------------------------

@pytest.fixture(scope="module")
def exporter():
    return make_unreal_fixture.load_exporter()


def test_exporter_imports_without_unreal(exporter):
    assert "unreal" not in sys.modules
    assert (exporter.FORMAT, exporter.VERSION) == (unreal_import.FORMAT, unreal_import.VERSION)


class CurveScene:
    """A scene whose camera follows a cubic in time; records the call order."""

    def __init__(self, exporter):
        self.x, self.frame, self.log = exporter, None, []

    def go_to(self, frame):
        self.frame = frame
        self.log.append(("go_to", frame))

    def camera(self, label):
        self.log.append(("camera", self.frame))
        f = self.frame
        return self.x.CameraSample((f ** 3 * 0.5, 0.0, 150.0), (0.0, -5.0, 0.1 * f * f), 40.0, (36.0, 24.0))

    def transform(self, label):
        self.log.append((label, self.frame))
        return self.x.TransformSample((800.0, 10.0 * self.frame, 0.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))


def test_sampling_reads_every_frame_after_moving_the_playhead(exporter):
    scene = CurveScene(exporter)
    samples = exporter.sample_frames(scene, [10, 11, 12, 13], 10, 30.0, "Cam", ["AdvBin"])
    assert scene.log[:3] == [("go_to", 10), ("AdvBin", 10), ("camera", 10)]
    assert [s.camera.location_cm[0] for s in samples] == [500.0, 665.5, 864.0, 1098.5]  # the cubic itself
    assert [s.time for s in samples] == pytest.approx([0.0, 1 / 30, 2 / 30, 3 / 30])


def test_export_round_trips_through_the_importer(exporter, tmp_path):
    config = exporter.check_config({"camera": "Cam", "object": {"actor": "AdvBin", "asset": {
        "name": "bin", "mesh": "builtin:trash_bin"}}})
    samples = exporter.sample_frames(CurveScene(exporter), [10, 11], 10, 30.0, "Cam", ["AdvBin"])
    path = tmp_path / "export.json"
    exporter.write_export(exporter.build_export(config, "/Game/Seq/Curve", 30.0, (48, 32), samples), path)
    seq = sequence_from_unreal(path)
    assert seq.name == "Curve" and [f.index for f in seq.frames] == [10, 11]
    assert seq.frames[1].camera.to_world.translation == pytest.approx((6.655, 1.5, 0.0))
    assert seq.frames[1].object_to_world.translation == pytest.approx((8.0, 0.0, 1.1))
    assert seq.frames[0].camera.film is None  # 48×32 is the filmback's 3:2


@pytest.mark.parametrize("config, message", [
    ({"object": {"actor": "A", "asset": {}}}, "config.camera"),
    ({"camera": "Cam", "object": {"actor": "A"}}, "config.object"),
    ({"camera": "Cam", "object": {"actor": "A", "asset": {}}, "actors": [{"asset": {}}]}, "config.actors[0]"),
    ({"camera": "Cam", "object": {"actor": "A", "asset": {}}, "lights": []}, "config.lights: unknown field"),
])
def test_exporter_config_errors(exporter, config, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        exporter.check_config(config)


def test_frame_numbers(exporter):
    assert exporter.frame_numbers(-2, 3) == [-2, -1, 0, 1, 2]
    assert exporter.frame_numbers(0, 10, every=4) == [0, 4, 8]
    with pytest.raises(ValueError, match="empty"):
        exporter.frame_numbers(5, 5)


def test_exporter_arguments(exporter):
    args = exporter.parse_args(["--sequence", "/Game/S", "--config", "c.json", "--out", "o.json",
                                "--resolution", "64", "36"])
    assert (args.sequence, args.resolution, args.mrq_config, args.every) == ("/Game/S", [64, 36], None, 1)
    with pytest.raises(SystemExit):
        exporter.parse_args(["--sequence", "/Game/S", "--config", "c.json", "--out", "o.json"])


def fake_unreal(positions: dict[int, float]) -> types.ModuleType:
    """The slice of Unreal's Python API the exporter calls, answering from ``positions``."""
    u = types.ModuleType("unreal")
    state = {"frame": None}

    class Vec:
        def __init__(self, x, y, z):
            self.x, self.y, self.z = x, y, z

    class Rot:
        def __init__(self, roll, pitch, yaw):
            self.roll, self.pitch, self.yaw = roll, pitch, yaw

    class Actor:
        def __init__(self, label):
            self.label = label

        def get_actor_label(self):
            return self.label

        def get_actor_location(self):
            return Vec(800.0, positions[state["frame"]], 0.0)

        def get_actor_rotation(self):
            return Rot(0.0, 0.0, 30.0)

        def get_actor_scale3d(self):
            return Vec(1.0, 1.0, 1.0)

        def get_component_by_class(self, cls):
            return CineCameraComponent()

    class CineCameraComponent:
        def get_world_location(self):
            return Vec(0.0, 0.0, 150.0)

        def get_world_rotation(self):
            return Rot(0.0, -5.0, 0.0)

        def get_horizontal_field_of_view(self):
            return 40.0

        def get_editor_property(self, name):
            return {"filmback": types.SimpleNamespace(sensor_width=36.0, sensor_height=24.0),
                    "constrain_aspect_ratio": False}[name]

    class LevelSequence:
        def get_display_rate(self):
            return types.SimpleNamespace(numerator=30, denominator=1)

        def get_playback_start(self):
            return min(positions)

        def get_playback_end(self):
            return max(positions) + 1

        def get_bindings(self):
            return ["cam", "bin"]

        def get_binding_id(self, binding):
            return binding

    class Lib:
        @staticmethod
        def open_level_sequence(seq):
            state["open"] = seq

        @staticmethod
        def set_global_position(params, unit):
            state["frame"] = params.frame

        @staticmethod
        def get_bound_objects(binding_id):
            return [Actor({"cam": "Cam", "bin": "AdvBin"}[binding_id])]

        @staticmethod
        def close_level_sequence():
            state["open"] = None

    u.LevelSequence, u.Actor, u.CineCameraComponent = LevelSequence, Actor, CineCameraComponent
    u.LevelSequenceEditorBlueprintLibrary = Lib
    u.load_asset = lambda path: LevelSequence() if path == "/Game/Seq/Fake" else None
    u.FrameNumber = lambda n: n
    u.FrameTime = lambda n: n
    u.MovieSceneSequencePlaybackParams = lambda frame, **kw: types.SimpleNamespace(frame=frame, **kw)
    u.MovieScenePositionType = types.SimpleNamespace(FRAME="frame")
    u.UpdatePositionMethod = types.SimpleNamespace(JUMP="jump")
    u.MovieSceneTimeUnit = types.SimpleNamespace(DISPLAY_RATE="display")
    u.state = state
    return u


def test_exporter_main_with_a_stand_in_for_unreal(exporter, tmp_path, monkeypatch):
    positions = {0: -100.0, 1: -40.0, 2: 75.0, 3: 90.0}  # not a straight line
    fake = fake_unreal(positions)
    monkeypatch.setitem(sys.modules, "unreal", fake)
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"camera": "Cam", "object": {"actor": "AdvBin", "asset": {
        "name": "bin", "mesh": "builtin:trash_bin"}}}))
    out = tmp_path / "out.json"
    exporter.main(["--sequence", "/Game/Seq/Fake", "--config", str(config), "--out", str(out),
                   "--resolution", "64", "36"])
    assert fake.state["open"] is None  # closed again
    data = json.loads(out.read_text())
    assert [f["transforms"]["AdvBin"]["location"][1] for f in data["frames"]] == list(positions.values())
    seq = sequence_from_unreal(out)
    assert [f.index for f in seq.frames] == [0, 1, 2, 3] and seq.fps == 30.0
