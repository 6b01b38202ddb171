"""``undream run --out``: validated before anything is written; --force replaces only a run's own folder."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

import scheduler.local
from farm_support import claim_during_preflight, make_scene, make_victim, run_config, write_yaml
from scheduler.preflight import check_output_folder, is_run_output
from undream.cli import main
from undream.errors import SpecError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene_dir(example_scenes):
    return example_scenes["bin_park"]


def _run(run_yaml: Path, out: Path, force: bool = True) -> subprocess.CompletedProcess:
    args = [sys.executable, "-m", "undream.cli", "run", str(run_yaml), "--out", str(out), "--no-progress"]
    return subprocess.run(args + (["--force"] if force else []), capture_output=True, text=True, cwd=ROOT)


def _config(tmp_path: Path, scene: Path, **changes) -> Path:
    cfg = {"name": "rules", "scene": str(scene), "victim": "bundled:classifier", "loss": "ce",
           "attack": {"name": "pgd", "eps": 8, "steps": 1}, "sim_spp": 1, "grad_spp": 1, "eval_spp": 1, **changes}
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _user_folder(path: Path) -> dict[str, str]:
    path.mkdir(parents=True)
    files = {"thesis.tex": "years of work", "data.csv": "1,2,3"}
    for name, text in files.items():
        (path / name).write_text(text)
    return files


def _intact(path: Path, files: dict[str, str]) -> bool:
    return all((path / n).read_text() == t for n, t in files.items())


def _one_line(res: subprocess.CompletedProcess, *needles: str) -> str:
    assert res.returncode == 2, res.stderr
    line = res.stderr.strip()
    assert "\n" not in line, line
    for n in needles:
        assert n in line, (n, line)
    return line


def test_force_never_deletes_a_folder_undream_did_not_write(scene_dir, tmp_path):
    out = tmp_path / "mine"
    files = _user_folder(out)
    _one_line(_run(_config(tmp_path, scene_dir), out), str(out), "--force", "metadata.json")
    assert _intact(out, files)


def test_a_bad_config_deletes_nothing_even_with_force(scene_dir, tmp_path):
    """A misspelt attack, with --force on an earlier run's folder: the error comes first, the folder stays."""
    out = tmp_path / "earlier_run"
    files = _user_folder(out)
    (out / "metadata.json").write_text(json.dumps({"run_id": "r-earlier"}))
    assert is_run_output(out)
    _one_line(_run(_config(tmp_path, scene_dir, attack={"name": "pgdd", "eps": 8, "steps": 1}), out), "pgdd")
    assert _intact(out, files)


def test_out_must_not_hold_the_scene(scene_dir, tmp_path):
    for out in (scene_dir, scene_dir.parent):
        _one_line(_run(_config(tmp_path, scene_dir), out), "holds the run's scene")
    assert (scene_dir / "sequence.json").is_file()


def test_an_unknown_label_is_rejected_before_out_exists(scene_dir, tmp_path):
    out = tmp_path / "new_out"
    _one_line(_run(_config(tmp_path, scene_dir, label="giraffe"), out, force=False), "label", "giraffe")
    assert not out.exists()


def test_force_replaces_an_earlier_run_and_marks_the_new_one(scene_dir, tmp_path):
    out = tmp_path / "again"
    out.mkdir()
    (out / "metadata.json").write_text(json.dumps({"undream_output": "run", "status": "started"}))
    (out / "stale.txt").write_text("from a crashed run")
    res = _run(_config(tmp_path, scene_dir), out)
    assert res.returncode == 0, res.stderr
    assert not (out / "stale.txt").exists()
    assert is_run_output(out) and (out / "results.json").is_file()


def test_check_output_folder_rules(tmp_path):
    scene = tmp_path / "proj" / "scene"
    scene.mkdir(parents=True)
    check_output_folder(tmp_path / "fresh", scene, force=False)  # a new folder is fine
    with pytest.raises(SpecError, match="holds the run's scene"):
        check_output_folder(tmp_path / "proj", scene, force=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(SpecError, match="not a folder"):
        check_output_folder(tmp_path / "file", scene, force=True)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "a").write_text("x")
    with pytest.raises(SpecError, match="already exists"):
        check_output_folder(tmp_path / "full", scene, force=False)


def _binary(tmp_path: Path) -> Path:
    p = tmp_path / "binary.yaml"
    p.write_bytes(bytes(range(256)) * 2)
    return p


BAD_RUNS = {
    "binary_run_config": (lambda t, s: _binary(t), ["binary.yaml", "not a text file"]),
    "targeted_at_own_class": (lambda t, s: _config(t, s, loss="targeted_ce", target_label="trash_bin"),
                              ["target_label", "trash_bin", "own class"]),
    "frames_per_step_beyond_the_sequence": (
        lambda t, s: _config(t, s, attack={"name": "pgd", "eps": 8, "steps": 1, "frames_per_step": 50}),
        ["attack.frames_per_step", "50", "8 frames"]),
    "cuda_on_a_cpu_build": (lambda t, s: _config(t, s, device="cuda"), ["device", "cuda", "use 'cpu'"]),
}


@pytest.mark.parametrize("case", sorted(BAD_RUNS))
def test_bad_runs_are_one_line_and_write_nothing(case, scene_dir, tmp_path):
    import torch

    if case == "cuda_on_a_cpu_build" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA: the case is about CPU builds of torch")
    make, needles = BAD_RUNS[case]
    out = tmp_path / "out"
    _one_line(_run(make(tmp_path, scene_dir), out, force=False), *needles)
    assert not out.exists()


def test_out_below_a_file_is_one_line(scene_dir, tmp_path):
    (tmp_path / "afile").write_text("x")
    _one_line(_run(_config(tmp_path, scene_dir), tmp_path / "afile" / "out", force=False), "afile", "is a file")


def test_a_binary_spec_is_one_line_for_init(tmp_path):
    res = subprocess.run([sys.executable, "-m", "undream.cli", "init", str(_binary(tmp_path)), "--out",
                          str(tmp_path / "scene")], capture_output=True, text=True, cwd=ROOT)
    _one_line(res, "binary.yaml", "not a text file")
    assert not (tmp_path / "scene").exists()


def test_outputs_are_replaced_whole_or_not_at_all(tmp_path):
    """A write that dies half-way leaves the earlier file as it was, and no temporary file."""
    from undream.spec.io import atomic_write  # what scheduler.outputs writes with

    target = tmp_path / "results.json"
    target.write_text('{"old": true}')

    def dies(f):
        f.write(b'{"new": ')
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, dies)
    assert target.read_text() == '{"old": true}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 2-frame scene and a tiny local victim (no network, seconds to check)."""
    base = tmp_path_factory.mktemp("tiny")
    return {"scene": make_scene(base / "scene", n_frames=2), "victim": make_victim(base / "victim")}


def test_two_runs_on_one_new_out_the_later_refuses_and_deletes_nothing(tiny, tmp_path, monkeypatch):
    """Issue 41: two `undream run` on the same new --out (no --force), the second started a second
    after the first: both checks passed while the folder did not exist, and the second then removed
    the first's live folder. The race made deterministic: the first run claims the folder while the
    second loads its victim (between its check and its first write). The second refuses in one line;
    every file of the first is as it was."""
    out = tmp_path / "out"
    winner = {"metadata.json": json.dumps({"undream_output": "run", "status": "started"}) + "\n",
              "store/runs.db": "the first run's store", "scene/sequence.json": "{}"}
    claim_during_preflight(monkeypatch, scheduler.local, out, winner)
    cfg = write_yaml(tmp_path / "run.yaml", run_config(tiny["scene"], tiny["victim"], steps=1))
    res = CliRunner().invoke(main, ["run", str(cfg), "--out", str(out), "--no-progress"],
                             env={"HF_HUB_OFFLINE": "1"})
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert f"--out {out}: another command claimed this folder" in lines[0], res.output
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == sorted(winner)
    assert all((out / name).read_text() == text for name, text in winner.items())


def test_an_empty_out_is_claimed_by_the_one_run_that_writes_it(tiny, tmp_path):
    """The claim leaves a lone run as it was: an existing empty --out is written without --force."""
    out = tmp_path / "empty"
    out.mkdir()
    res = _run(write_yaml(tmp_path / "run.yaml", run_config(tiny["scene"], tiny["victim"], steps=1)), out, force=False)
    assert res.returncode == 0, res.stderr[-3000:]
    assert is_run_output(out) and (out / "results.json").is_file()
