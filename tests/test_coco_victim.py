"""coco:centernet, a real COCO detector read from its TF.js graph: parity with the
official TF.js runtime on real photographs, what it finds in them, its gradients,
and bad inputs (an op the loader does not know, weights of another shape, a
class COCO does not have, a model setup has not fetched), one line each."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import service_missing
from undream.errors import VictimError
from undream.settings import load_local
from undream.victims import Target, load_victim
from undream.victims.coco import COCO_LABELS, MODELS, model_path
from undream.victims.tfjs import GraphModule, read_graph_model

REPO = Path(__file__).resolve().parents[1]
TFJS = REPO / "deploy" / "tfjs"
CACHE_HOME = load_local().cache_home
CACHE = Path(CACHE_HOME) / "undream"
PARITY_PHOTOS = ("dog", "person", "horses", "bus", "zidane")
SIZE = MODELS["centernet"].input_size


@pytest.fixture(scope="module")
def model_json() -> Path:
    path = model_path("centernet", CACHE)
    if not path.is_file():
        service_missing(f"{path} is missing: run ./deploy/setup.sh (deploy/fetch_models.py)")
    return path


@pytest.fixture(scope="module")
def victim(model_json: Path):
    return load_victim("coco:centernet", cache_home=CACHE_HOME)


def photo(name: str, size: int | None = None) -> torch.Tensor:
    """A fetched photograph as sRGB [0, 1] ``1×3×H×W`` (resized to size² by PIL if given)."""
    path = CACHE / "photos" / f"{name}.jpg"
    if not path.is_file():
        service_missing(f"{path} is missing: run ./deploy/setup.sh (deploy/fetch_models.py)")
    img = Image.open(path).convert("RGB")
    if size:
        img = img.resize((size, size), Image.BILINEAR)
    return torch.from_numpy(np.asarray(img, dtype=np.float32) / 255).permute(2, 0, 1)[None]


def test_parity_with_tfjs_on_real_photographs(model_json: Path, tmp_path: Path) -> None:
    """The torch port and the official TF.js runtime (CPU backend, under node) agree on
    five real photographs: class scores to 1e-4, box distances to 1e-4 of their range."""
    if shutil.which("node") is None or not (TFJS / "node_modules" / "@tensorflow" / "tfjs-converter").is_dir():
        service_missing("node and deploy/tfjs/node_modules are needed: run ./deploy/setup.sh")
    spec = MODELS["centernet"]
    inputs = []
    for name in PARITY_PHOTOS:
        x = (photo(name, SIZE) * 255).permute(0, 2, 3, 1).contiguous()
        inputs.append(x)
        x.numpy().astype("<f4").tofile(tmp_path / f"{name}.f32")
    job = {"model": str(model_json), "input": spec.input, "shape": [1, SIZE, SIZE, 3],
           "inputs": [str(tmp_path / f"{n}.f32") for n in PARITY_PHOTOS],
           "outputs": [spec.scores, spec.boxes], "out_dir": str(tmp_path / "tfjs")}
    (tmp_path / "job.json").write_text(json.dumps(job))
    done = subprocess.run(["node", str(TFJS / "run_graph.cjs"), str(tmp_path / "job.json")],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    manifest = json.loads((tmp_path / "tfjs" / "outputs.json").read_text())
    graph = GraphModule(read_graph_model(model_json), [spec.scores, spec.boxes], spec.input)
    for name, x, row in zip(PARITY_PHOTOS, inputs, manifest):
        with torch.no_grad():
            ours = graph(x)
        for out in (spec.scores, spec.boxes):
            ref = np.fromfile(tmp_path / "tfjs" / row[out]["file"], "<f4").reshape(row[out]["shape"])
            got = ours[out].numpy()
            assert got.shape == ref.shape
            err = float(np.abs(got - ref).max())
            scale = 1.0 if out == spec.scores else float(np.abs(ref).max())
            assert err <= 1e-4 * scale, f"{name} {out}: max |Δ| {err} (scale {scale})"


@pytest.mark.parametrize("name,cls,least", [("person", "person", 0.5), ("horses", "horse", 0.5),
                                            ("dog", "dog", 0.3), ("bus", "bus", 0.3), ("zidane", "person", 0.3)])
def test_finds_objects_in_real_photographs(victim, name: str, cls: str, least: float) -> None:
    pred = victim.predict(photo(name))[0]
    found = [float(s) for s, lab in zip(pred.scores, pred.labels) if COCO_LABELS[int(lab)] == cls]
    assert found and max(found) >= least, [(COCO_LABELS[int(lab)], float(s)) for s, lab in
                                          zip(pred.scores, pred.labels)]


def test_predictions_box_the_object_in_input_pixels(victim) -> None:
    """The horse's box is in the photograph's pixels (not the 512² model input's)."""
    x = photo("person")
    pred = victim.predict(x)[0]
    person = next(b for b, lab in zip(pred.boxes, pred.labels) if COCO_LABELS[int(lab)] == "person")
    h, w = x.shape[-2:]
    x0, y0, x1, y1 = person.tolist()
    assert 0 <= x0 < x1 <= w + 5 and 0 <= y0 < y1 <= h + 5
    assert 150 < (x0 + x1) / 2 < 300 and (y1 - y0) > h / 2  # the standing woman, left of centre


@pytest.mark.parametrize("kind,target", [("vanish", Target(label=0, box=(186, 109, 275, 375))),
                                         ("mislabel", Target(label=0, target_label=16, box=(186, 109, 275, 375))),
                                         ("box", Target(label=0, box=(186, 109, 275, 375)))])
def test_losses_reach_every_pixel(victim, kind: str, target: Target) -> None:
    x = photo("person").requires_grad_(True)
    loss = victim.loss(x, target, kind)
    loss.backward()
    assert torch.isfinite(loss) and x.grad is not None and torch.isfinite(x.grad).all()
    assert float((x.grad != 0).float().mean()) > 0.99


def test_vanish_ascent_lowers_the_score(victim) -> None:
    """Three signed-gradient steps on the vanish loss lower the person's best score."""
    x = photo("person", 256)
    target = Target(label=0, box=(186 * 256 / 640, 109 * 256 / 424, 275 * 256 / 640, 375 * 256 / 424))

    def best(img: torch.Tensor) -> float:  # the person's best score over every candidate (no NMS cut)
        with torch.no_grad():
            return float(victim.forward_raw(img).log_probs[..., 0].exp().max())

    before, adv = best(x), x.clone()
    for _ in range(3):
        adv.requires_grad_(True)
        victim.loss(adv, target, "vanish").backward()
        adv = (adv + 8 / 255 * adv.grad.sign()).clamp(0, 1).detach()
    assert best(adv) < before - 0.1


def _copy_model(model_json: Path, dest: Path) -> Path:
    out = dest / "models" / "centernet"
    out.mkdir(parents=True)
    for f in model_json.parent.iterdir():
        shutil.copy(f, out / f.name)
    return out


def test_unknown_op_is_one_line_naming_it(model_json: Path, tmp_path: Path) -> None:
    folder = _copy_model(model_json, tmp_path / "undream")
    doc = json.loads((folder / "centernet.json").read_text())
    node = next(n for n in doc["modelTopology"]["node"] if n["op"] == "Relu6")
    node["op"] = "Softplus9"
    (folder / "centernet.json").write_text(json.dumps(doc))
    with pytest.raises(VictimError) as err:
        load_victim("coco:centernet", cache_home=str(tmp_path))
    msg = str(err.value)
    assert "'Softplus9'" in msg and node["name"] in msg and "\n" not in msg


def test_weights_of_another_shape_are_refused(model_json: Path, tmp_path: Path) -> None:
    folder = _copy_model(model_json, tmp_path / "undream")
    data = (folder / "centernet.bin").read_bytes()
    (folder / "centernet.bin").write_bytes(data[:-1000])
    with pytest.raises(VictimError, match="weights of another shape") as err:
        load_victim("coco:centernet", cache_home=str(tmp_path))
    assert "\n" not in str(err.value)


def test_missing_model_says_to_run_setup(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match=r"deploy/setup\.sh"):
        load_victim("coco:centernet", cache_home=str(tmp_path))


def test_unknown_coco_model_lists_the_valid_ones(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match="coco:centernet"):
        load_victim("coco:yolo9000", cache_home=str(tmp_path))


def test_run_check_refuses_a_class_coco_does_not_have(model_json: Path, tmp_path: Path) -> None:
    """Through the command: the bin is no COCO class; refused in one line, nothing written."""
    config = tmp_path / "run.yaml"
    config.write_text(f"name: coco_bin\nscene: {REPO / 'examples' / 'bin_orbit.yaml'}\nvictim: coco:centernet\n"
                      "loss: vanish\nattack: {name: pgd, eps: 16, steps: 1}\nlabel: trash can\n")
    out = tmp_path / "out"
    env = {**os.environ, "XDG_CACHE_HOME": CACHE_HOME}
    done = subprocess.run([str(REPO / ".venv" / "bin" / "undream"), "run", str(config), "--out", str(out),
                           "--check"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode != 0
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "trash can" in lines[0] and "label" in lines[0], done.stderr
    assert not out.exists()


def test_stop_sign_plate_is_cocos_stop_sign_by_default(model_json: Path) -> None:
    """The example stop sign (the plate as the object, the pole an actor) needs no label: the
    built-in part takes the whole's class, and stop_sign reads as COCO's 'stop sign'."""
    from undream.engine.context import class_ids
    from undream.spec.run import RunConfig

    from undream.scene.sources import sequence_from_file

    seq = sequence_from_file(REPO / "examples" / "stop_sign_street.yaml")
    config = RunConfig.from_json({"name": "s", "scene": "x", "victim": "coco:centernet", "loss": "vanish",
                                  "attack": {"name": "pgd", "eps": 16, "steps": 1}})
    victim = load_victim("coco:centernet", cache_home=CACHE_HOME)
    assert class_ids(config, seq, victim) == (COCO_LABELS.index("stop sign"), None)
