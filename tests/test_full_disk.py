"""A full disk ends a command with one line naming the file, and leaves nothing half-written (issue 41).

Before: ``undream init``, ``run``, ``report`` and ``evaluate --json`` on a full disk printed 37–52
lines of traceback ending in ``OSError: [Errno 28] No space left on device`` (a write's error names
no file) or Mitsuba's ``RuntimeError: [FileStream] ...``.

Two ways to fill a disk:

- a real one: each command runs in its own mount namespace (``unshare -m``) on a small tmpfs
  mounted there, so no mount outlives the test. Needs root (CAP_SYS_ADMIN); skipped, saying so,
  where the machine refuses it;
- a simulated one, on every machine: every file opened for writing under a folder fails its
  writes with ``ENOSPC`` (``builtins.open`` and ``os.fdopen`` patched), through click's CliRunner.
"""
from __future__ import annotations

import builtins
import errno
import io
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from farm_support import ROOT, make_scene, make_victim, run_config, write_yaml
from undream.cli import main

FILES = "--- files ---"
SPEC = {"name": "ball", "frames": 4,
        "camera": {"fov": 40, "resolution": [32, 32], "path": {"type": "orbit", "radius": 4, "height": 1}},
        "object": {"asset": {"name": "ball", "mesh": "builtin:sphere"}, "path": {"type": "static", "position": [0, 0, 0]}}}


def _can_mount() -> str | None:
    """None when this process may mount a tmpfs in a mount namespace of its own, else why not."""
    if shutil.which("unshare") is None:
        return "no unshare(1) on this machine"
    probe = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                           capture_output=True, text=True)
    return None if probe.returncode == 0 else f"cannot mount a tmpfs here: {probe.stderr.strip()}"


NO_MOUNT = _can_mount()
needs_mount = pytest.mark.skipif(NO_MOUNT is not None, reason=f"a real full disk needs a tmpfs: {NO_MOUNT}")


def _on_a_small_disk(disk: Path, size_kb: int, *commands: list[str], before: str = "",
                     grow_kb: int | None = None) -> tuple[list[subprocess.CompletedProcess], list[str]]:
    """Run each ``undream`` command in turn with a ``size_kb`` tmpfs mounted on ``disk`` (in a mount
    namespace of its own); ``before``: shell lines run on the fresh disk first; ``grow_kb``: the disk
    grows to that size after the first command (space freed). Each command's exit status and
    streams, and the files left on the disk (relative paths, sorted)."""
    disk.mkdir(exist_ok=True)
    undream = [sys.executable, "-m", "undream.cli"]
    steps = []
    for i, argv in enumerate(commands):
        if i == 1 and grow_kb is not None:
            steps.append(f"mount -o remount,size={grow_kb}k {disk}")
        line = " ".join(f"'{a}'" for a in [*undream, *argv])
        steps.append(f"{line} >{disk.parent}/out{i}.txt 2>{disk.parent}/err{i}.txt; echo $? >{disk.parent}/rc{i}.txt")
    script = "\n".join([f"mount -t tmpfs -o size={size_kb}k tmpfs {disk} || exit 99", f"cd {disk}", before,
                        *steps, f"cd {disk} && find . -type f | sort"])
    res = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, cwd=ROOT,
                         timeout=600, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert res.returncode == 0, res.stderr
    done = [subprocess.CompletedProcess(argv, int((disk.parent / f"rc{i}.txt").read_text()),
                                        (disk.parent / f"out{i}.txt").read_text(),
                                        (disk.parent / f"err{i}.txt").read_text())
            for i, argv in enumerate(commands)]
    return done, [line[2:] for line in res.stdout.splitlines()]


def _full_disk_line(res: subprocess.CompletedProcess, disk: Path) -> str:
    """The command's last stderr line: exit 2, the one error line naming a file on ``disk`` and the
    disk being full, and no traceback."""
    assert res.returncode == 2, (res.returncode, res.stderr[-3000:])
    assert "Traceback" not in res.stderr, res.stderr[-3000:]
    line = res.stderr.strip().splitlines()[-1]
    assert line.startswith("undream: error: ") and str(disk) in line, line
    assert "No space left on device" in line or "database or disk is full" in line, line
    return line


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("full_disk")
    scene = make_scene(root / "scene", n_frames=2, size=16)
    victim = make_victim(root / "victim")
    cfg = write_yaml(root / "run.yaml", run_config(scene, victim, steps=2))
    out = root / "done"
    res = subprocess.run([sys.executable, "-m", "undream.cli", "run", str(cfg), "--out", str(out), "--no-progress"],
                         capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    return {"root": root, "scene": scene, "victim": victim, "run": cfg, "done": out,
            "spec": write_yaml(root / "spec.yaml", SPEC)}


@needs_mount
def test_init_on_a_full_disk_names_the_file_and_leaves_nothing(tiny, tmp_path):
    disk = tmp_path / "disk"
    for size in (8, 80, 160):  # the mesh, the texture, the verification renders (a 32 px, 4-frame scene)
        (res,), files = _on_a_small_disk(disk, size, ["init", str(tiny["spec"]), "--out", str(disk / "scene"),
                                                      "--no-progress"])
        line = _full_disk_line(res, disk / "scene")
        assert "No space left on device" in line
        assert files == [], (size, files)  # the temporary folder is gone, no scene half-written


@needs_mount
def test_run_on_a_full_disk_is_one_line_and_resumes_when_space_is_freed(tiny, tmp_path):
    """Full at the store (SQLite), then at the output files: one line naming the file each time; the
    folder stays a run's, and `undream run --resume` finishes it once the disk has room."""
    disk = tmp_path / "disk"
    out = disk / "out"
    run = ["run", str(tiny["run"]), "--out", str(out), "--no-progress"]
    for size in (300, 460):
        (first, again), files = _on_a_small_disk(disk, size, run, [*run, "--resume"], grow_kb=8192)
        line = _full_disk_line(first, disk)
        assert str(out) in line
        assert again.returncode == 0, again.stderr[-3000:]
        assert {"out/metadata.json", "out/results.json", "out/texture_final.png", "out/loss.png"} <= set(files)
        assert not [f for f in files if f.endswith(".tmp")], files  # no temporary file left behind


@needs_mount
def test_report_on_a_full_disk_names_the_file_and_leaves_nothing(tiny, tmp_path):
    disk = tmp_path / "disk"
    for size in (8, 40):
        (res,), files = _on_a_small_disk(disk, size, ["report", str(tiny["done"]), "--out", str(disk / "rep")])
        line = _full_disk_line(res, disk / "rep")
        assert "No space left on device" in line
        assert files == [], files


@needs_mount
def test_evaluate_outputs_on_a_full_disk_keep_the_earlier_files(tiny, tmp_path):
    """--json and --csv after every render: one line naming the file; the earlier file is as it was."""
    disk = tmp_path / "disk"
    texture = str(tiny["done"] / "texture_final.npy")
    common = ["evaluate", texture, str(tiny["scene"]), "--victim", tiny["victim"], "--spp", "1"]
    fill = "printf 'earlier' > r.json; printf 'earlier' > r.csv; dd if=/dev/zero of=filler bs=4k count=64 2>/dev/null"
    (json_out, csv_out), files = _on_a_small_disk(disk, 64, [*common, "--json", str(disk / "r.json")],
                                                  [*common, "--csv", str(disk / "r.csv")], before=fill)
    assert "No space left on device" in _full_disk_line(json_out, disk / "r.json")
    assert "No space left on device" in _full_disk_line(csv_out, disk / "r.csv")
    assert files == ["filler", "r.csv", "r.json"], files  # no temporary file left


class _FullFile:
    """A file opened for writing on a simulated full disk: every write fails as write(2) would."""

    def __init__(self, f):
        self._f = f

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()


def _simulated_full_disk(monkeypatch, folder: Path) -> None:
    """Every file opened for writing under ``folder`` fails its writes with ENOSPC (no file name,
    as the kernel reports it): ``builtins.open`` (Pillow, numpy), ``io.open`` (Path.write_*) and
    ``os.fdopen`` (atomic writes) patched."""
    real_open, real_fdopen = builtins.open, os.fdopen

    def writing(mode) -> bool:
        return any(c in str(mode) for c in "wax+")

    def full_open(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        inside = isinstance(file, (str, Path)) and Path(file).resolve().is_relative_to(folder)
        return _FullFile(f) if inside and writing(mode) else f

    def full_fdopen(fd, mode="r", *args, **kwargs):
        f = real_fdopen(fd, mode, *args, **kwargs)
        inside = Path(os.readlink(f"/proc/self/fd/{fd}")).is_relative_to(folder)
        return _FullFile(f) if inside and writing(mode) else f

    monkeypatch.setattr(builtins, "open", full_open)
    monkeypatch.setattr(io, "open", full_open)
    monkeypatch.setattr(os, "fdopen", full_fdopen)


def test_report_on_a_simulated_full_disk_names_the_file(tiny, tmp_path, monkeypatch):
    folder = tmp_path / "full"
    folder.mkdir()
    _simulated_full_disk(monkeypatch, folder)
    res = CliRunner().invoke(main, ["report", str(tiny["done"]), "--out", str(folder / "rep")])
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert lines[0].startswith(f"undream: error: {folder / 'rep'}/") and "No space left on device" in lines[0]
    assert list(folder.iterdir()) == []


def test_evaluate_json_on_a_simulated_full_disk_keeps_the_earlier_file(tiny, tmp_path, monkeypatch):
    folder = tmp_path / "full"
    folder.mkdir()
    (folder / "r.json").write_text("earlier")
    texture = tmp_path / "t.npy"
    np.save(texture, np.load(tiny["done"] / "texture_final.npy"))
    _simulated_full_disk(monkeypatch, folder)
    res = CliRunner().invoke(main, ["evaluate", str(texture), str(tiny["scene"]), "--victim", tiny["victim"],
                                    "--spp", "1", "--json", str(folder / "r.json")], env={"HF_HUB_OFFLINE": "1"})
    assert res.exit_code == 2, res.output
    assert res.output.strip().splitlines()[-1] == f"undream: error: {folder / 'r.json'}: No space left on device"
    assert [p.name for p in folder.iterdir()] == ["r.json"] and (folder / "r.json").read_text() == "earlier"
