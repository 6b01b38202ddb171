"""RUN.yaml: validation with named fields, JSON round trip, scene references checked."""
import json

import pytest
import yaml

from undream.errors import SpecError
from undream.spec.run import RunConfig, load_run_config


def test_round_trip():
    cfg = RunConfig(scene="s", victim="bundled:detector", loss="mislabel", target_label="car",
                    attack={"name": "apgd", "eps": 16}, torch_threads=2, store="sqlite:///x.db")
    assert RunConfig.from_json(json.loads(json.dumps(cfg.to_json()))) == cfg


@pytest.mark.parametrize("field, value, message", [
    ("loss", "hinge", "loss: must be one of"),
    ("sim_spp", 0, "sim_spp: 0 is out of range (valid: 1 ≤ sim_spp ≤ 65536)"),
    ("torch_threads", 0, "torch_threads"),
    ("victim_batch", 0, "victim_batch"),
    ("attack", {"eps": 3}, "attack.name: "),
    ("seed", -1, "seed"),
])
def test_bad_fields_are_named(field, value, message):
    with pytest.raises(SpecError) as err:
        RunConfig.from_json({"scene": "s", field: value})
    assert str(err.value).startswith(message), str(err.value)


def test_scene_is_resolved_against_the_file(tmp_path):
    (tmp_path / "spec.yaml").write_text("frames: 1\n")
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({"scene": "spec.yaml"}))
    assert load_run_config(tmp_path / "run.yaml").scene == "spec.yaml"
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({"scene": "missing"}))
    with pytest.raises(SpecError, match=r"run.yaml: scene: .*missing is neither a scene directory"):
        load_run_config(tmp_path / "run.yaml")
