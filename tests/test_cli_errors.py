"""Bad input to ``undream init``: one line naming file and field, exit 2, nothing written."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _spec(mesh="builtin:sphere", position=(0, 0, 0)):
    return {"name": "bad", "frames": 2, "camera": {"fov": 40, "resolution": [16, 16],
                                                   "path": {"type": "static", "position": [0, 1, 4]}},
            "object": {"asset": {"name": "thing", "mesh": mesh}, "path": {"type": "static", "position": list(position)}}}


def _run(spec_path: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "undream.cli", "init", str(spec_path), "--out", str(out),
                           "--no-progress", "--verify-spp", "1"], capture_output=True, text=True, cwd=ROOT)


def _write(tmp_path: Path, name: str, content) -> Path:
    p = tmp_path / name
    p.write_text(content if isinstance(content, str) else yaml.safe_dump(content))
    return p


CASES = {
    "missing_mesh": (lambda t: _write(t, "s.yaml", _spec(mesh="nowhere/missing.obj")),
                     ["s.yaml", "asset.mesh", "missing.obj", "not found"]),
    "mesh_without_uvs": (lambda t: (_write(t, "flat.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
                                    _write(t, "s.yaml", _spec(mesh="flat.obj")))[1],
                         ["s.yaml", "asset.mesh", "flat.obj", "UV"]),
    "unknown_asset": (lambda t: _write(t, "s.yaml", _spec(mesh="builtin:teapot")),
                      ["s.yaml", "asset.mesh", "teapot", "sphere"]),
    "nan_in_pose": (lambda t: _write(t, "s.yaml", _spec(position=(float("nan"), 0, 0))),
                    ["s.yaml", "object.path.position[0]", "finite"]),
    "bad_yaml": (lambda t: _write(t, "s.yaml", "frames: [1,\n"), ["s.yaml", "YAML", "line"]),
    "missing_spec": (lambda t: t / "nothing.yaml", ["nothing.yaml", "not found"]),
    "unreal_missing_frames": (lambda t: _write(t, "ue.json", '{"format": "undream-unreal-export", "version": 1}'),
                              ["ue.json", "is required"]),
    "unreal_nan_rotation": (lambda t: _write(t, "ue.json", (ROOT / "examples/unreal/drive_by_export.json").read_text()
                                             .replace('"rotation": [', '"rotation": [NaN, ', 1)),
                            ["ue.json", "rotation"]),
}


@pytest.mark.parametrize("content, needles", [
    ("scene: x\nloss: hinge\n", ["run.yaml", "loss", "hinge"]),
    ("scene: nowhere/scene\n", ["run.yaml", "scene", "neither a scene directory nor a spec file"]),
    ("scene: x\nattack: {steps: 3}\n", ["run.yaml", "attack.name", "required"]),
    ("scene: x\nloss: targeted_ce\n", ["run.yaml", "target_label", "required"]),
    ("scene: x\nepsilon: 3\n", ["run.yaml", "epsilon", "unknown field"]),
])
def test_bad_run_config_is_one_line(content, needles, tmp_path):
    spec = _write(tmp_path, "run.yaml", content)
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(spec), "--out", str(tmp_path / "out"),
                          "--no-progress"], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2, res.stderr
    line = res.stderr.strip()
    assert "\n" not in line
    for needle in needles:
        assert needle in line, (needle, line)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_and_writes_nothing(case, tmp_path):
    make, needles = CASES[case]
    spec = make(tmp_path)
    out = tmp_path / "out"
    before = sorted(p.name for p in tmp_path.iterdir())
    res = _run(spec, out)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing half-written
