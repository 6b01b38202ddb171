"""Checked before anything is written: memory of huge cameras, read-only folders, mesh paths, ``--check``.

Before: a 16384² camera ran until memory gave out (4 GB and climbing after
40 s), a read-only ``--out`` was a traceback (init) or "no permission"
(run), a mesh that broke a spec file of a run was only found after OUT was
made, and nothing said where a mesh outside the spec's folder came from.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from undream.errors import SpecError
from undream.render.budget import RenderJob, check_renders
from undream.settings import parse_bytes

ROOT = Path(__file__).resolve().parents[1]


def _undream(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-m", "undream.cli", *args], capture_output=True, text=True,
                          cwd=ROOT, env={**os.environ, **(env or {})})


def _one_line(res: subprocess.CompletedProcess, *needles: str) -> str:
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    line = res.stderr.strip()
    assert "\n" not in line, line
    for needle in needles:
        assert needle in line, (needle, line)
    return line


def _spec(resolution=(16, 16), mesh="builtin:sphere") -> dict:
    return {"name": "rules", "frames": 2, "camera": {"fov": 40, "resolution": list(resolution),
                                                     "path": {"type": "static", "position": [0, 1, 4]}},
            "object": {"asset": {"name": "thing", "mesh": mesh}, "path": {"type": "static", "position": [0, 0, 0]}}}


def _write(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def _run_yaml(tmp_path: Path, scene: Path) -> Path:
    return _write(tmp_path / "run.yaml", {"name": "rules", "scene": str(scene), "victim": "bundled:classifier",
                                          "loss": "ce", "attack": {"name": "pgd", "eps": 8, "steps": 1},
                                          "sim_spp": 1, "grad_spp": 1, "eval_spp": 1})


# -- memory ----------------------------------------------------------------------------------------


def test_a_huge_camera_is_refused_before_anything_renders(tmp_path):
    """A 16384² camera needs about 27 GB; the limit is pinned so that the test does not depend on the machine."""
    spec = _write(tmp_path / "huge.yaml", _spec((16384, 16384)))
    limit = {"UNDREAM_MEMORY_LIMIT": "16G"}
    line = _one_line(_undream("init", str(spec), "--out", str(tmp_path / "scene"), "--verify-spp", "4", env=limit),
                     "huge.yaml", "frames[0].camera.resolution", "16384×16384", "GB of memory")
    assert "UNDREAM_MEMORY_LIMIT" in line
    run = _run_yaml(tmp_path, spec)
    _one_line(_undream("run", str(run), "--out", str(tmp_path / "out"), env=limit), "run.yaml", "huge.yaml",
              "camera.resolution", "16384×16384")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.yaml", "run.yaml"]


def test_more_samples_than_mitsuba_can_index_are_refused():
    with pytest.raises(SpecError, match=r"sim_spp: 65536×65536 px at 1 spp is 4,294,967,296 samples"):
        check_renders([RenderJob("sim_spp", 65536, 65536, 1)], limit=2**62)


def test_the_memory_limit_refuses_what_does_not_fit_and_names_the_biggest_render():
    small, big = RenderJob("a", 64, 64, 8), RenderJob("frames[3].camera.resolution", 2048, 2048, 8)
    peak = check_renders([small, big], limit=2**40)
    assert peak == big.peak_bytes and peak > 2048 * 2048 * 90
    with pytest.raises(SpecError, match=r"frames\[3\].camera.resolution: 2048×2048 px at 8 spp needs about"):
        check_renders([small, big], limit=peak - 1)
    assert parse_bytes("8G") == 8 << 30 and parse_bytes("512MiB") == 512 << 20 and parse_bytes("100") == 100
    with pytest.raises(SpecError, match="UNDREAM_MEMORY_LIMIT: 'lots' is not a size"):
        parse_bytes("lots")


def test_the_memory_limit_comes_from_the_environment(tmp_path):
    spec = _write(tmp_path / "s.yaml", _spec((64, 64)))
    _one_line(_undream("init", str(spec), "--out", str(tmp_path / "scene"), "--check",
                       env={"UNDREAM_MEMORY_LIMIT": "1M"}), "s.yaml", "1.05 MB is available")
    ok = _undream("init", str(spec), "--out", str(tmp_path / "scene"), "--check", env={"UNDREAM_MEMORY_LIMIT": "1G"})
    assert ok.returncode == 0 and "nothing written" in ok.stdout and not (tmp_path / "scene").exists()


# -- --check ---------------------------------------------------------------------------------------


def test_check_validates_everything_and_writes_nothing(tmp_path):
    spec = _write(tmp_path / "s.yaml", _spec())
    run = _run_yaml(tmp_path, spec)
    res = _undream("run", str(run), "--out", str(tmp_path / "out"), "--check")
    assert res.returncode == 0, res.stderr
    assert "M samples per iteration" in res.stdout and "nothing written" in res.stdout
    bad = _write(tmp_path / "bad.yaml", yaml.safe_load(run.read_text()) | {"label": "giraffe"})
    _one_line(_undream("run", str(bad), "--out", str(tmp_path / "out"), "--check"), "bad.yaml", "giraffe")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml", "run.yaml", "s.yaml"]


def test_a_mesh_without_uvs_in_a_runs_spec_is_refused_before_out_exists(tmp_path):
    _write(tmp_path / "flat.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    spec = _write(tmp_path / "s.yaml", _spec(mesh="flat.obj"))
    out = tmp_path / "out"
    _one_line(_undream("run", str(_run_yaml(tmp_path, spec)), "--out", str(out)), "run.yaml", "s.yaml",
              "asset.mesh", "flat.obj", "UV")
    assert not out.exists()


# -- read-only file systems ------------------------------------------------------------------------


def test_a_read_only_out_is_one_line_for_init_and_run(read_only, tmp_path):
    spec = _write(tmp_path / "s.yaml", _spec())
    for args in (["init", str(spec)], ["run", str(_run_yaml(tmp_path, spec))]):
        _one_line(_undream(*args, "--out", str(read_only / "out")), f"--out {read_only / 'out'}",
                  "read-only file system")


# -- mesh paths ------------------------------------------------------------------------------------


def test_a_mesh_outside_the_specs_folder_is_copied_in_and_its_source_recorded(tmp_path):
    """The rule: relative paths resolve against the spec's folder (.. included), absolute ones as they
    are; the mesh is copied into the scene directory, which refers to nothing outside itself."""
    lib = tmp_path / "library" / "meshes"
    quad = "v -0.5 0 0\nv 0.5 0 0\nv 0.5 1 0\nv -0.5 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n"
    _write(lib / "quad.obj", quad)
    spec = _write(tmp_path / "specs" / "s.yaml", _spec(mesh="../library/meshes/quad.obj"))
    out = tmp_path / "scene"
    res = _undream("init", str(spec), "--out", str(out), "--verify-spp", "1", "--no-progress")
    assert res.returncode == 0, res.stderr
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["mesh_sources"] == {"object": str((lib / "quad.obj").resolve())}
    for xml in (out / "frames").glob("*.xml"):
        assert "library" not in xml.read_text() and str(tmp_path) not in xml.read_text()
    assert (out / "meshes" / "object.ply").is_file()
