"""The benign evaluation once: a sweep over seeds renders the scene's own texture once (counted), a
change of anything in the key renders it again, and a run reads the same numbers with or without it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from farm_support import make_scene, make_victim
from undream.settings import LocalSettings
from undream.spec.run import RunConfig

N_FRAMES = 3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mi):
    root = tmp_path_factory.mktemp("benign")
    return {"root": root, "victim": make_victim(root / "victim"), "scene": make_scene(root / "scene", N_FRAMES, 16)}


@pytest.fixture
def renders(monkeypatch):
    """Every evaluation render of this process: (frame position, whether the texture was the benign one)."""
    from undream.engine import algorithm

    seen: list[tuple[int, bool]] = []
    real = algorithm.eval_render

    def counted(ctx, position, texture):
        benign = algorithm.quantise(algorithm.start_texture(ctx))
        seen.append((position, bool(np.array_equal(texture, benign))))
        return real(ctx, position, texture)

    monkeypatch.setattr(algorithm, "eval_render", counted)
    return seen


def _config(tiny, seed=0, **fields):
    return RunConfig.from_json({"scene": str(tiny["scene"]), "name": f"s{seed}", "victim": tiny["victim"],
                                "loss": "ce", "attack": {"name": "pgd", "eps": 32.0, "steps": 1},
                                "sim_spp": 2, "grad_spp": 2, "eval_spp": 2, "seed": seed, **fields})


def _run(config, out, local):
    from scheduler.local import run_local

    return run_local(config, out, progress=False, local=local)


def _benign_renders(renders) -> int:
    return sum(1 for _, benign in renders if benign)


def test_a_sweep_over_seeds_renders_the_benign_frames_once(tiny, tmp_path, renders):
    local = LocalSettings(cache_home=str(tmp_path / "cache"))
    results = [_run(_config(tiny, seed), tmp_path / f"seed{seed}", local) for seed in range(4)]
    assert _benign_renders(renders) == N_FRAMES  # once for the sweep, not once per run
    assert len(renders) == N_FRAMES * 5  # and each run's own adversarial frames
    key = results[0]["benign_cache"]["key"]
    assert [r["benign_cache"] for r in results] == \
        [{"key": key, "frames_from_cache": 0, "frames_rendered": N_FRAMES}] + \
        [{"key": key, "frames_from_cache": N_FRAMES, "frames_rendered": 0}] * 3
    assert len({json.dumps(r["benign"], sort_keys=True) for r in results}) == 1
    assert (tmp_path / "cache" / "undream" / "benign" / key / "key.json").is_file()
    pngs = [sorted((tmp_path / f"seed{s}" / "frames_benign").glob("*.png")) for s in range(4)]
    assert len(pngs[0]) == N_FRAMES
    for other in pngs[1:]:  # the frames the report and dashboard show: the same bytes
        assert [p.read_bytes() for p in other] == [p.read_bytes() for p in pngs[0]]


def test_a_run_reads_the_same_benign_numbers_with_the_cache_on_and_off(tiny, tmp_path, renders):
    from undream.store import open_store

    cache = str(tmp_path / "cache")
    on = [_run(_config(tiny, 1), tmp_path / f"on{i}", LocalSettings(cache_home=cache)) for i in range(2)]
    off = _run(_config(tiny, 1), tmp_path / "off", LocalSettings(cache_home=cache, benign_cache=False))
    assert on[1]["benign_cache"]["frames_from_cache"] == N_FRAMES and off["benign_cache"] is None
    assert _benign_renders(renders) == 2 * N_FRAMES  # the first run and the one with the cache off
    for block in ("benign", "attacked", "held_out", "attack_success"):
        assert on[1][block] == off[block] == on[0][block], block
    frames = {}
    for name, res in (("on1", on[1]), ("off", off)):
        with open_store(None, tmp_path / name / "store") as store:
            jobs = store.jobs(res["run_id"], 1, "pre")
            frames[name] = ([store.blobs.get_array(j.image_ref) for j in jobs],
                            [j.result["prediction"] for j in jobs])
    assert all(np.array_equal(a, b) for a, b in zip(frames["on1"][0], frames["off"][0]))
    assert frames["on1"][1] == frames["off"][1]


def test_anything_in_the_key_renders_the_benign_frames_again(tiny, tmp_path, renders):
    local = LocalSettings(cache_home=str(tmp_path / "cache"))
    other_victim = make_victim(tmp_path / "victim2")  # the same architecture and seed: the same weights
    import torch
    from transformers import ResNetForImageClassification

    model = ResNetForImageClassification.from_pretrained(other_victim)
    with torch.no_grad():
        next(model.parameters()).add_(0.01)  # one weight changed, the name's folder the same kind
    model.save_pretrained(other_victim)
    keys = []
    for i, fields in enumerate(({}, {"seed": 7, "attack": {"name": "pgd", "eps": 8.0, "steps": 1}},
                                {"eval_spp": 3}, {"victim": other_victim}, {"victim_batch": 2})):
        res = _run(_config(tiny, **fields), tmp_path / f"run{i}", local)
        keys.append((res["benign_cache"]["key"], res["benign_cache"]["frames_rendered"]))
    # A run of another seed or attack reads the first run's frames; another eval_spp, victim or
    # victim batch renders and judges them again.
    assert [n for _, n in keys] == [N_FRAMES, 0, N_FRAMES, N_FRAMES, N_FRAMES]
    assert keys[0][0] == keys[1][0] and len({k for k, _ in keys}) == 4
    assert _benign_renders(renders) == 4 * N_FRAMES


def test_runs_that_initialise_the_same_spec_share_the_benign_frames(tiny, tmp_path, renders):
    """Each run initialises its own scene from the spec (a new metadata.json each time): one key."""
    local = LocalSettings(cache_home=str(tmp_path / "cache"))
    spec = str(tiny["scene"] / "sequence.json")
    res = [_run(_config(tiny, seed, scene=spec), tmp_path / f"spec{seed}", local) for seed in (0, 1)]
    assert [r["benign_cache"]["frames_rendered"] for r in res] == [N_FRAMES, 0]
    assert _benign_renders(renders) == N_FRAMES


def test_the_key_holds_the_scene_the_texture_and_the_simulator(tiny, tmp_path):
    """Key documents differ where the scene's files, the benign texture or the simulator differ."""
    from scheduler.benign import benign_key, key_document, scene_digest
    from undream.engine.context import build_context

    ctx = build_context(_config(tiny), tiny["scene"])
    texture = np.full((8, 16, 3), 0.5, np.float32)
    base = key_document(ctx, scene_digest(ctx.scene_dir), texture)
    assert benign_key(base) == benign_key(key_document(ctx, scene_digest(ctx.scene_dir), texture.copy()))
    assert base["eval_seed"][0] == 0 and base["sim_versions"]["variant"]
    changed = [key_document(ctx, "another scene", texture), key_document(ctx, base["scene"], texture * 0.5),
               {**base, "sim_versions": {**base["sim_versions"], "mitsuba": "0.0.0"}}, {**base, "frozen": False}]
    assert len({benign_key(d) for d in [base, *changed]}) == 5


def test_a_sweep_over_seeds_on_a_farm_worker_renders_the_benign_frames_once(tiny, tmp_path):
    """`undream sweep` of 4 seeds served by a real worker process: the runs' own records say that
    the benign frames were rendered and judged once, in the farm's blob store, for the whole sweep."""
    from conftest import service_missing
    from farm_support import Farm, finished_runs, redis_up, wait_for, write_yaml

    reason = redis_up()
    if reason:
        service_missing(reason)
    farm = Farm(tmp_path / "farm")
    farm.root.mkdir()
    try:
        run = {"scene": str(tiny["scene"]), "victim": tiny["victim"], "loss": "ce", "sim_spp": 2, "grad_spp": 2,
               "eval_spp": 2, "attack": {"name": "pgd", "eps": 32.0, "steps": 1}}
        write_yaml(farm.root / "run.yaml", run)
        sweep = write_yaml(farm.root / "sweep.yaml", {"name": "seeds", "run": "run.yaml", "grid": {"seed": [0, 1, 2, 3]}})
        res = farm.cli("sweep", str(sweep))
        assert res.returncode == 0, res.stderr
        sweep_id = res.stdout.splitlines()[0]
        farm.start_worker()
        wait_for(lambda: finished_runs(farm.store, 4), 300, "the sweep's 4 runs")
        runs = farm.store.runs(sweep_id=sweep_id)
        assert [r.status for r in runs] == ["done"] * 4, [(r.status, r.error) for r in runs]
        records = [r.results["benign_cache"] for r in runs]
        assert sum(r["frames_rendered"] for r in records) == N_FRAMES, records
        assert sum(r["frames_from_cache"] for r in records) == 3 * N_FRAMES
        assert len({r["key"] for r in records}) == 1
        assert len({json.dumps(r.results["benign"], sort_keys=True) for r in runs}) == 1
        assert (farm.blobs / "benign" / records[0]["key"] / "key.json").is_file()
    finally:
        farm.stop()


def test_the_cache_is_turned_off_by_one_variable_for_the_farm_and_undream_run():
    from scheduler.options import FarmOptions
    from undream.settings import SettingsError, load_local, load_settings

    assert load_settings(env={}).benign_cache is True and load_local({}).benign_cache is True
    off = {"UNDREAM_BENIGN_CACHE": "0"}
    assert load_settings(env=off).benign_cache is False and load_local(off).benign_cache is False
    assert FarmOptions(benign_cache=False).to_json()["benign_cache"] is False
    assert "benign_cache" not in FarmOptions().to_json()  # on: stored as runs before the cache were
    with pytest.raises(SettingsError, match="UNDREAM_BENIGN_CACHE: must be true or false"):
        load_local({"UNDREAM_BENIGN_CACHE": "maybe"})


def test_a_batch_reads_the_cache_only_whole_and_judged_in_the_same_batch(tmp_path):
    """The victim's batches decide float rounding: frames kept from another batch are computed again."""
    from scheduler.benign import BenignCache, CachedFrame
    from undream.store import BlobStore

    cache = BenignCache(BlobStore(tmp_path), {"scene": "s"})
    frames = [CachedFrame(np.full((2, 2, 3), i, np.uint8), {"label": i, "score": 0.5 + i / 8}) for i in range(2)]
    cache.put([0, 1], frames)
    got = cache.get([0, 1])
    assert [f.prediction for f in got] == [f.prediction for f in frames]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(got, frames))
    assert cache.get([0]) is None and cache.get([1, 2]) is None and cache.get([1, 0]) is None
    assert BenignCache(BlobStore(tmp_path), {"scene": "t"}).get([0, 1]) is None  # another key
    (tmp_path / "benign" / cache.key / "0001.json").write_text("{")  # a torn or foreign entry
    assert cache.get([0, 1]) is None
