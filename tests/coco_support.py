"""What the tests of the real COCO detectors (coco:centernet, coco:nanodet) share: the
fetched model and photographs, the official TF.js runtime run under node, and the checks
every such victim must pass (its parity, its gradients, bad model files one line each)."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import service_missing
from undream.errors import VictimError
from undream.settings import load_local
from undream.victims import Target, load_victim
from undream.victims.coco import MODELS, model_path
from undream.victims.tfjs import GraphModule, read_graph_model

REPO = Path(__file__).resolve().parents[1]
TFJS = REPO / "deploy" / "tfjs"
CACHE_HOME = load_local().cache_home
CACHE = Path(CACHE_HOME) / "undream"
PARITY_PHOTOS = ("dog", "person", "horses", "bus", "zidane")


def fetched_model(name: str) -> Path:
    """The ``model.json`` of ``coco:NAME`` in the cache; skipped (failed under CI) when setup did not fetch it."""
    path = model_path(name, CACHE)
    if not path.is_file():
        service_missing(f"{path} is missing: run ./deploy/setup.sh (deploy/fetch_models.py)")
    return path


def photo(name: str, size: int | None = None) -> torch.Tensor:
    """A fetched photograph as sRGB [0, 1] ``1×3×H×W`` (resized to size² by PIL if given)."""
    path = CACHE / "photos" / f"{name}.jpg"
    if not path.is_file():
        service_missing(f"{path} is missing: run ./deploy/setup.sh (deploy/fetch_models.py)")
    img = Image.open(path).convert("RGB")
    if size:
        img = img.resize((size, size), Image.BILINEAR)
    return torch.from_numpy(np.asarray(img, dtype=np.float32) / 255).permute(2, 0, 1)[None]


def assert_parity(model_json: Path, inputs: dict[str, torch.Tensor], input_name: str, outputs: list[str],
                  exact: set[str], tmp_path: Path) -> None:
    """The graph run by undream and by the official TF.js runtime (CPU backend, under node) on
    ``inputs`` (photo name → the graph's input tensor): outputs in ``exact`` agree to 1e-4, the
    others to 1e-4 of their largest magnitude."""
    if shutil.which("node") is None or not (TFJS / "node_modules" / "@tensorflow" / "tfjs-converter").is_dir():
        service_missing("node and deploy/tfjs/node_modules are needed: run ./deploy/setup.sh")
    for name, x in inputs.items():
        x.numpy().astype("<f4").tofile(tmp_path / f"{name}.f32")
    shape = list(next(iter(inputs.values())).shape)
    job = {"model": str(model_json), "input": input_name, "shape": shape,
           "inputs": [str(tmp_path / f"{n}.f32") for n in inputs], "outputs": outputs,
           "out_dir": str(tmp_path / "tfjs")}
    (tmp_path / "job.json").write_text(json.dumps(job))
    done = subprocess.run(["node", str(TFJS / "run_graph.cjs"), str(tmp_path / "job.json")],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    manifest = json.loads((tmp_path / "tfjs" / "outputs.json").read_text())
    graph = GraphModule(read_graph_model(model_json), outputs, input_name)
    for (name, x), row in zip(inputs.items(), manifest):
        with torch.no_grad():
            ours = graph(x)
        for out in outputs:
            ref = np.fromfile(tmp_path / "tfjs" / row[out]["file"], "<f4").reshape(row[out]["shape"])
            got = ours[out].numpy()
            assert got.shape == ref.shape
            err = float(np.abs(got - ref).max())
            scale = 1.0 if out in exact else float(np.abs(ref).max())
            assert err <= 1e-4 * scale, f"{name} {out}: max |Δ| {err} (scale {scale})"


def assert_finds(victim: Any, name: str, cls: str, least: float) -> None:
    """The victim finds ``cls`` in the photograph ``name`` with a score of at least ``least``."""
    pred = victim.predict(photo(name))[0]
    found = [float(s) for s, lab in zip(pred.scores, pred.labels) if victim.labels[int(lab)] == cls]
    assert found and max(found) >= least, [(victim.labels[int(lab)], float(s)) for s, lab in
                                          zip(pred.scores, pred.labels)]


def assert_losses_reach_every_pixel(victim: Any, kind: str, target: Target) -> None:
    x = photo("person").requires_grad_(True)
    loss = victim.loss(x, target, kind)
    loss.backward()
    assert torch.isfinite(loss) and x.grad is not None and torch.isfinite(x.grad).all()
    assert float((x.grad != 0).float().mean()) > 0.99


def assert_vanish_ascent_lowers_the_score(victim: Any, person: tuple[float, float, float, float]) -> None:
    """Three signed-gradient steps on the vanish loss lower the best person score of person.jpg
    (640×424, the woman at ``person`` in its pixels) at 256², by more than 0.1."""
    x = photo("person", 256)
    target = Target(label=0, box=tuple(v * 256 / s for v, s in zip(person, (640, 424, 640, 424))))

    def best(img: torch.Tensor) -> float:  # the person's best score over every candidate (no NMS cut)
        with torch.no_grad():
            return float(victim.forward_raw(img).log_probs[..., 0].exp().max())

    before, adv = best(x), x.clone()
    for _ in range(3):
        adv.requires_grad_(True)
        victim.loss(adv, target, "vanish").backward()
        adv = (adv + 8 / 255 * adv.grad.sign()).clamp(0, 1).detach()
    assert best(adv) < before - 0.1


def copied_model(name: str, model_json: Path, cache_home: Path) -> Path:
    """A copy of ``coco:NAME``'s files in the model cache under ``cache_home``; its folder."""
    spec = MODELS[name]
    out = cache_home / "undream" / "models" / spec.folder
    out.mkdir(parents=True)
    for f in model_json.parent.iterdir():
        shutil.copy(f, out / f.name)
    return out


def assert_unknown_op_is_one_line(name: str, model_json: Path, tmp_path: Path, op: str) -> None:
    """A copy whose first ``op`` node is renamed: loading it names the new op and the node, on one line."""
    graph = copied_model(name, model_json, tmp_path) / MODELS[name].model_json
    doc = json.loads(graph.read_text())
    node = next(n for n in doc["modelTopology"]["node"] if n["op"] == op)
    node["op"] = op + "9"
    graph.write_text(json.dumps(doc))
    with pytest.raises(VictimError) as err:
        load_victim(f"coco:{name}", cache_home=str(tmp_path))
    msg = str(err.value)
    assert f"'{op}9'" in msg and node["name"] in msg and "\n" not in msg


def assert_short_weights_are_refused(name: str, model_json: Path, tmp_path: Path) -> None:
    folder = copied_model(name, model_json, tmp_path)
    weights = next(folder.glob("*.bin"))
    weights.write_bytes(weights.read_bytes()[:-1000])
    with pytest.raises(VictimError, match="weights of another shape") as err:
        load_victim(f"coco:{name}", cache_home=str(tmp_path))
    assert "\n" not in str(err.value)
