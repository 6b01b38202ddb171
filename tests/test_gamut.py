"""The printable-gamut constraint (issue 44): a CMYK profile's round trip made a true projection,
``gamut`` in the run config, and a run whose steps are projected (docs/printing.md).

Tests of the projection use the profile ``deploy/setup.sh`` fetched into this machine's cache (skipped,
saying so, where it did not); the config's refusals need no profile.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from undream.errors import PrintError, SpecError
from undream.printing.profiles import default_profile, resolve_gamut
from undream.settings import load_local
from undream.spec.run import RunConfig, load_run_config

CACHE = load_local().undream_cache
PROFILE = default_profile(CACHE)
needs_profile = pytest.mark.skipif(not PROFILE.is_file(), reason=f"the CMYK profile is not in {PROFILE}: run "
                                   "./deploy/setup.sh (or .venv/bin/python deploy/fetch_profiles.py)")
BLUE, GREEN = (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)


@pytest.fixture(scope="module")
def gamut():
    from undream.printing.gamut import load_gamut

    if not PROFILE.is_file():
        pytest.skip(f"the CMYK profile is not in {PROFILE}: run ./deploy/setup.sh")
    return load_gamut(PROFILE)


def _random(shape=(64, 48, 3), seed=0) -> np.ndarray:
    return np.random.default_rng(seed).random(shape).astype(np.float32)


# -- the projection ---------------------------------------------------------------------------------

@needs_profile
def test_the_projection_is_idempotent_bit_for_bit(gamut):
    x = _random()
    once = gamut.project(x)
    assert once.dtype == np.float32 and once.shape == x.shape
    assert not np.array_equal(once, x)  # random sRGB colours are mostly not printable
    assert np.array_equal(gamut.project(once), once)
    q = (np.rint(once * 255) / 255).astype(np.float32)  # the 8-bit texture a run writes
    assert np.array_equal(gamut.project(q), q)
    assert gamut.contains(once).all()


@needs_profile
def test_printable_colours_come_back_unchanged(gamut):
    from undream.printing.gamut import round_trip

    x = gamut.project(_random(seed=1))
    x = np.clip(x + np.random.default_rng(2).uniform(-0.4, 0.4, x.shape) / 255, 0, 1).astype(np.float32)
    keep = gamut.contains(x)  # colours that round to the same printable 8-bit texel
    assert keep.mean() > 0.9
    y = gamut.project(x)
    assert np.array_equal(y[keep], x[keep])  # bit for bit, not moved to the 8-bit grid
    # printable: the ICC round trip moves them at most the tolerance
    rgb8 = np.rint(x * 255).astype(np.uint8)
    moved = np.abs(round_trip(rgb8, gamut.profile).astype(int) - rgb8.astype(int)).max(axis=2)
    assert moved[keep].max() <= gamut.tolerance and moved[~keep].min() > gamut.tolerance


@needs_profile
def test_pure_blue_and_green_move_into_the_gamut(gamut):
    from undream.printing.gamut import round_trip

    x = np.array([[BLUE, GREEN, (1.0, 1.0, 1.0)]], dtype=np.float32)
    y = gamut.project(x)
    assert not gamut.contains(x)[0, :2].any() and gamut.contains(y).all()
    assert np.abs(y[0, 0] - x[0, 0]).max() > 0.25 and np.abs(y[0, 1] - x[0, 1]).max() > 0.25  # far out
    assert y[0, 0, 2] > y[0, 0, 0] and y[0, 1, 1] > y[0, 1, 0]  # still a blue and a green
    assert np.array_equal(y[0, 2], x[0, 2])  # paper white prints
    y8 = np.rint(y * 255).astype(np.uint8)
    assert np.abs(round_trip(y8, gamut.profile).astype(int) - y8.astype(int)).max() <= gamut.tolerance
    # P lands within a few levels of the ICC round trip itself
    x8 = np.rint(x * 255).astype(np.uint8)
    assert np.abs(y8.astype(int) - round_trip(x8, gamut.profile).astype(int)).max() <= 8


@needs_profile
def test_bad_textures_are_one_line(gamut):
    with pytest.raises(PrintError, match=r"texture: must be sRGB H×W×3 floats"):
        gamut.project(np.zeros((4, 4), np.float32))
    with pytest.raises(PrintError, match=r"texture: values must be finite and in \[0, 1\]"):
        gamut.project(np.full((2, 2, 3), 1.5, np.float32))


# -- profiles and the run config -------------------------------------------------------------------

def test_bad_gamut_values_are_refused_by_the_config():
    assert RunConfig(scene="s").gamut == "none"
    for bad in ("bogus", 3, "sRGB.png", None):
        with pytest.raises(SpecError, match=r"^gamut: must be default \(the CMYK profile setup fetched\), none, "
                                            r"or the path of a CMYK printer profile"):
            RunConfig.from_json({"scene": "s", "gamut": bad})


def _icc(path: Path, space: bytes = b"CMYK", device: bytes = b"prtr", magic: bytes = b"acsp") -> Path:
    head = bytearray(128)
    head[12:16], head[16:20], head[36:40] = device, space, magic
    path.write_bytes(bytes(head) + b"\0" * 64)
    return path


def test_bad_profiles_are_one_line(tmp_path):
    cases = [
        (tmp_path / "missing.icc", r"gamut: .*missing\.icc: no such profile"),
        (_icc(tmp_path / "rgb.icc", space=b"RGB "), r"gamut: .*rgb\.icc: a profile of RGB colours, not CMYK"),
        (_icc(tmp_path / "scan.icc", device=b"scnr"), r"gamut: .*scan\.icc: a CMYK profile of device class 'scnr'"),
        (_icc(tmp_path / "junk.icc", magic=b"nope"), r"gamut: .*junk\.icc: not an ICC profile"),
    ]
    for path, message in cases:
        with pytest.raises(SpecError, match=message) as err:
            resolve_gamut(str(path), tmp_path)
        assert "\n" not in str(err.value)
    with pytest.raises(SpecError, match=r"gamut: default: the CMYK profile .*profiles/ghostscript/default_cmyk\.icc "
                                        r"is not there; \./deploy/setup\.sh fetches it"):
        resolve_gamut("default", tmp_path / "empty-cache")
    assert resolve_gamut("none", tmp_path) is None


def test_a_header_that_littlecms_cannot_read_is_one_line(tmp_path):
    from undream.printing.gamut import load_gamut

    with pytest.raises(SpecError, match=r"gamut: .*fake\.icc: littleCMS cannot (read the profile|convert sRGB to and from it) \("):
        load_gamut(_icc(tmp_path / "fake.icc"))


def test_the_run_config_file_checks_its_profile_before_anything_is_written(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "sequence.json").write_text("{}")
    run = tmp_path / "run.yaml"
    run.write_text("scene: scene\ngamut: profiles/printer.icc\n")
    with pytest.raises(SpecError, match=rf"^{run}: gamut: .*printer\.icc: no such profile"):
        load_run_config(run)
    _icc(tmp_path / "profiles" / "printer.icc", space=b"GRAY") if (tmp_path / "profiles").mkdir() is None else None
    with pytest.raises(SpecError, match=r"a profile of GRAY colours, not CMYK"):
        load_run_config(run)
    _icc(tmp_path / "profiles" / "printer.icc")
    assert load_run_config(run).gamut == str((tmp_path / "profiles" / "printer.icc").resolve())  # relative to the file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profiles", "run.yaml", "scene"]


def test_a_sweep_reads_profiles_beside_its_file(tmp_path):
    from scheduler.sweep import load_sweep

    (tmp_path / "sweep.yaml").write_text("name: s\nbase: {scene: scene}\ngrid: {gamut: [none, default, p.icc]}\n")
    with pytest.raises(SpecError, match=r"sweep\.yaml: run 2 \(gamut='p\.icc'\): gamut: .*p\.icc: no such profile"):
        load_sweep(tmp_path / "sweep.yaml")
    _icc(tmp_path / "p.icc")
    runs = load_sweep(tmp_path / "sweep.yaml").runs
    assert [r.config.gamut for r in runs] == ["none", "default", str((tmp_path / "p.icc").resolve())]


def test_undream_run_refuses_a_bad_gamut_before_writing(tmp_path):
    from click.testing import CliRunner

    from undream.cli import main

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "sequence.json").write_text("{}")
    (tmp_path / "run.yaml").write_text("scene: scene\ngamut: printer.png\n")
    res = CliRunner().invoke(main, ["run", str(tmp_path / "run.yaml"), "--out", str(tmp_path / "out"), "--no-progress"])
    assert res.exit_code == 2 and "gamut: must be default" in res.output
    assert not (tmp_path / "out").exists()


# -- a run ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    from farm_support import make_scene, make_victim

    base = tmp_path_factory.mktemp("gamut")
    return make_scene(base / "scene", n_frames=2, size=24), make_victim(base / "victim")


@needs_profile
def test_a_run_with_the_default_gamut_ends_on_a_printable_texture(tiny, tmp_path, gamut):
    import yaml
    from click.testing import CliRunner

    from farm_support import run_config
    from undream.cli import main

    scene, victim = tiny
    config = run_config(scene, victim, name="printable", steps=2, holdout="none", gamut="default",
                        attack={"eps": 64.0, "random_start": True})
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    res = CliRunner().invoke(main, ["run", str(tmp_path / "run.yaml"), "--out", str(tmp_path / "out"), "--no-progress"])
    assert res.exit_code == 0, res.output
    final = np.load(tmp_path / "out" / "texture_final.npy")
    assert np.array_equal(gamut.project(final), final)
    # the same run without the gamut ends on colours the printer cannot make: the projection did the work
    (tmp_path / "plain.yaml").write_text(yaml.safe_dump({**config, "gamut": "none"}))
    res = CliRunner().invoke(main, ["run", str(tmp_path / "plain.yaml"), "--out", str(tmp_path / "plain"),
                                    "--no-progress"])
    assert res.exit_code == 0, res.output
    assert not gamut.contains(np.load(tmp_path / "plain" / "texture_final.npy")).all()


def test_undream_run_refuses_a_default_gamut_that_setup_did_not_fetch(tmp_path):
    from click.testing import CliRunner

    from undream.cli import main

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "sequence.json").write_text("{}")
    (tmp_path / "run.yaml").write_text("scene: scene\ngamut: default\n")
    res = CliRunner(env={"XDG_CACHE_HOME": str(tmp_path / "empty-cache")}).invoke(
        main, ["run", str(tmp_path / "run.yaml"), "--out", str(tmp_path / "out"), "--no-progress"])
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        f"undream: error: {tmp_path / 'run.yaml'}: gamut: default: the CMYK profile "
        f"{tmp_path / 'empty-cache' / 'undream' / 'profiles' / 'ghostscript' / 'default_cmyk.icc'} is not there; "
        "./deploy/setup.sh fetches it (or .venv/bin/python deploy/fetch_profiles.py), or give a profile's path"]
    assert not (tmp_path / "out").exists() and not (tmp_path / "empty-cache").exists()


@needs_profile
def test_a_farm_run_projects_every_texture_version(tiny, tmp_path, gamut):
    """The farm's stages (start, the callback's step) with a process's context cache, as workers run them."""
    from farm_support import run_config
    from scheduler.contexts import ContextCache
    from scheduler.local import LocalDispatch, drain
    from scheduler.submit import Validator, record
    from undream.settings import load_settings
    from undream.store import open_store

    scene, victim = tiny
    config = RunConfig.from_json(run_config(scene, victim, name="farm-gamut", steps=2, holdout="none",
                                            gamut="default", attack={"eps": 64.0, "random_start": True}))
    settings = load_settings(env={"UNDREAM_DATABASE_URL": f"sqlite:///{tmp_path}/farm.db",
                                  "UNDREAM_BLOB_URL": str(tmp_path / "blobs")})
    store = open_store(settings.database_url, settings.blob_url)
    (run_id,) = record(store, [Validator(tmp_path / "work")(config, tmp_path)], settings, tmp_path / "out")
    dispatch = LocalDispatch()
    dispatch.start(run_id)
    drain(store, ContextCache(store, tmp_path / "cache", local=load_local()), dispatch)
    assert store.get_run(run_id).status == "done"
    versions = [store.texture(run_id, k) for k in range(3)] + [store.final_texture(run_id)]
    for T in versions:
        assert np.array_equal(gamut.project(T), T)
    assert not np.array_equal(versions[0], versions[2])  # the attack moved it, inside the gamut
