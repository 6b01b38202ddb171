"""undream's TF.js-graph reader on tiny hand-written graphs: known answers for
TensorFlow's SAME padding and legacy bilinear resize, float16 weights, the ops of
ONNX conversions (Transpose, Pad/PadV2, SplitV/Split, SparseToDense), and bad
graphs refused in one line."""
from __future__ import annotations

import base64
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from undream.errors import VictimError
from undream.victims.tfjs import GraphModule, check_outputs, read_graph_model


def _s(text: str) -> dict:
    return {"s": base64.b64encode(text.encode()).decode()}


def _ints(*v: int) -> dict:
    return {"list": {"i": [str(i) for i in v]}}


def write_model(folder: Path, nodes: list[dict], weights: dict[str, np.ndarray], half: bool = False) -> Path:
    """A TF.js graph model of ``nodes`` whose constants are ``weights`` (float16-quantised if ``half``)."""
    specs, blobs = [], []
    for name, arr in weights.items():
        spec = {"name": name, "shape": list(arr.shape), "dtype": "int32" if arr.dtype.kind == "i" else "float32"}
        if half and arr.dtype.kind == "f":
            spec["quantization"] = {"dtype": "float16", "original_dtype": "float32"}
            blobs.append(arr.astype("<f2").tobytes())
        else:
            blobs.append(arr.astype("<i4" if arr.dtype.kind == "i" else "<f4").tobytes())
        specs.append(spec)
    consts = [{"name": n, "op": "Const", "attr": {}} for n in weights]
    doc = {"format": "graph-model", "modelTopology": {"node": consts + nodes},
           "weightsManifest": [{"paths": ["w.bin"], "weights": specs}]}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "w.bin").write_bytes(b"".join(blobs))
    (folder / "model.json").write_text(json.dumps(doc))
    return folder / "model.json"


PLACEHOLDER = {"name": "x", "op": "Placeholder", "attr": {}}


def test_strided_same_conv_pads_after_as_tensorflow_does(tmp_path: Path) -> None:
    """A 3×3 stride-2 SAME conv of an even-sized input pads 0 before and 1 after (TF), not 1 and 1."""
    w = np.random.default_rng(0).normal(size=(3, 3, 2, 4)).astype(np.float32)
    b = np.arange(4, dtype=np.float32)
    conv = {"name": "y", "op": "_FusedConv2D", "input": ["x", "w", "b"],
            "attr": {"strides": _ints(1, 2, 2, 1), "padding": _s("SAME"), "data_format": _s("NHWC"),
                     "dilations": _ints(1, 1, 1, 1), "fused_ops": {"list": {"s": [_s("BiasAdd")["s"],
                                                                                   _s("Relu6")["s"]]}}}}
    g = GraphModule(read_graph_model(write_model(tmp_path, [PLACEHOLDER, conv], {"w": w, "b": b})), ["y"])
    x = torch.randn(1, 8, 8, 2)
    want = F.conv2d(F.pad(x.permute(0, 3, 1, 2), (0, 1, 0, 1)), torch.from_numpy(w).permute(3, 2, 0, 1),
                    torch.from_numpy(b), 2).clamp(0, 6).permute(0, 2, 3, 1)
    got = g(x)["y"]
    assert got.shape == (1, 4, 4, 4)
    assert torch.allclose(got, want, atol=1e-5)


def test_legacy_bilinear_resize_known_answer(tmp_path: Path) -> None:
    """align_corners and half_pixel_centers off: source = destination × in/out, edge clamped."""
    resize = {"name": "y", "op": "ResizeBilinear", "input": ["x", "size"],
              "attr": {"align_corners": {"b": False}, "half_pixel_centers": {"b": False}}}
    path = write_model(tmp_path, [PLACEHOLDER, resize], {"size": np.array([1, 8], dtype=np.int32)})
    x = torch.tensor([0.0, 1.0, 2.0, 3.0]).reshape(1, 1, 4, 1)
    got = GraphModule(read_graph_model(path), ["y"])(x)["y"].reshape(-1)
    assert got.tolist() == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.0]


def test_float16_weights_and_depthwise_conv(tmp_path: Path) -> None:
    w = np.random.default_rng(1).normal(size=(3, 3, 3, 1)).astype(np.float32)
    dw = {"name": "y", "op": "DepthwiseConv2dNative", "input": ["x", "w"],
          "attr": {"strides": _ints(1, 1, 1, 1), "padding": _s("VALID"), "data_format": _s("NHWC")}}
    g = GraphModule(read_graph_model(write_model(tmp_path, [PLACEHOLDER, dw], {"w": w}, half=True)), ["y"])
    x = torch.randn(1, 5, 5, 3)
    w16 = torch.from_numpy(w.astype(np.float16).astype(np.float32))
    want = F.conv2d(x.permute(0, 3, 1, 2), w16.permute(2, 3, 0, 1), groups=3).permute(0, 2, 3, 1)
    assert torch.allclose(g(x)["y"], want, atol=1e-5)


def test_unknown_op_named_before_anything_runs(tmp_path: Path) -> None:
    node = {"name": "y", "op": "FancyOp", "input": ["x"], "attr": {}}
    with pytest.raises(VictimError, match=r"op 'FancyOp' \(node 'y'\) is not supported") as err:
        GraphModule(read_graph_model(write_model(tmp_path, [PLACEHOLDER, node], {})), ["y"])
    assert "\n" not in str(err.value)


def test_short_weight_file_is_refused(tmp_path: Path) -> None:
    path = write_model(tmp_path, [PLACEHOLDER], {"w": np.ones((4, 4), np.float32)})
    (tmp_path / "w.bin").write_bytes(b"\0" * 20)
    with pytest.raises(VictimError, match="weights of another shape"):
        read_graph_model(path)


def test_long_weight_file_is_refused(tmp_path: Path) -> None:
    path = write_model(tmp_path, [PLACEHOLDER], {"w": np.ones((4,), np.float32)})
    (tmp_path / "w.bin").write_bytes(b"\0" * 64)
    with pytest.raises(VictimError, match="hold 64 bytes, the manifest's shapes need 16"):
        read_graph_model(path)


def test_not_a_graph_model(tmp_path: Path) -> None:
    (tmp_path / "model.json").write_text(json.dumps({"modelTopology": {"class_name": "Sequential"}}))
    with pytest.raises(VictimError, match="not a TF.js graph model"):
        read_graph_model(tmp_path)


def _graph(tmp_path: Path, nodes: list[dict], weights: dict[str, np.ndarray], outputs: list[str]) -> GraphModule:
    return GraphModule(read_graph_model(write_model(tmp_path, [PLACEHOLDER, *nodes], weights)), outputs)


def test_transpose_known_answer(tmp_path: Path) -> None:
    """NCHW → NHWC, as ONNX conversions do around each convolution."""
    node = {"name": "y", "op": "Transpose", "input": ["x", "perm"], "attr": {}}
    g = _graph(tmp_path, [node], {"perm": np.array([0, 2, 3, 1], np.int32)}, ["y"])
    x = torch.arange(24.0).reshape(1, 2, 3, 4)
    got = g(x)["y"]
    assert got.shape == (1, 3, 4, 2) and got[0, 2, 1].tolist() == [9.0, 21.0]


def test_pad_and_padv2_known_answer(tmp_path: Path) -> None:
    """Pad fills with 0; PadV2 with its value (-inf before a VALID max pool); pairs are (before, after)."""
    pad = {"name": "p", "op": "Pad", "input": ["x", "pads"], "attr": {}}
    pad2 = {"name": "q", "op": "PadV2", "input": ["x", "pads", "v"], "attr": {}}
    g = _graph(tmp_path, [pad, pad2], {"pads": np.array([[0, 0], [1, 2]], np.int32),
                                       "v": np.array(-np.inf, np.float32)}, ["p", "q"])
    out = g(torch.tensor([[1.0, 2.0]]))
    assert out["p"].tolist() == [[0.0, 1.0, 2.0, 0.0, 0.0]]
    assert out["q"].tolist() == [[-math.inf, 1.0, 2.0, -math.inf, -math.inf]]


def test_pad_of_another_rank_is_one_line(tmp_path: Path) -> None:
    pad = {"name": "p", "op": "Pad", "input": ["x", "pads"], "attr": {}}
    g = _graph(tmp_path, [pad], {"pads": np.array([[1, 1]], np.int32)}, ["p"])
    with pytest.raises(VictimError, match=r"node 'p' \(Pad\): paddings \[\[1, 1\]\] do not fit") as err:
        g(torch.zeros(2, 2))
    assert "\n" not in str(err.value)


def test_splitv_outputs_by_index_and_the_rest(tmp_path: Path) -> None:
    """SplitV with a -1 size (the rest); ``name:1`` is its second output, as TF.js names it."""
    split = {"name": "s", "op": "SplitV", "input": ["x", "sizes", "axis"], "attr": {"num_split": {"i": "2"}}}
    g = _graph(tmp_path, [split], {"sizes": np.array([1, -1], np.int32), "axis": np.array(1, np.int32)},
               ["s", "s:1"])
    out = g(torch.arange(8.0).reshape(2, 4))
    assert out["s"].tolist() == [[0.0], [4.0]]
    assert out["s:1"].tolist() == [[1.0, 2.0, 3.0], [5.0, 6.0, 7.0]]


def test_split_into_equal_pieces(tmp_path: Path) -> None:
    split = {"name": "s", "op": "Split", "input": ["axis", "x"], "attr": {"num_split": {"i": "2"}}}
    g = _graph(tmp_path, [split], {"axis": np.array(-1, np.int32)}, ["s", "s:1"])
    out = g(torch.arange(4.0).reshape(1, 4))
    assert out["s"].tolist() == [[0.0, 1.0]] and out["s:1"].tolist() == [[2.0, 3.0]]
    three = {"name": "t", "op": "Split", "input": ["axis", "x"], "attr": {"num_split": {"i": "3"}}}
    g3 = _graph(tmp_path / "3", [three], {"axis": np.array(1, np.int32)}, ["t"])
    with pytest.raises(VictimError, match=r"node 't' \(Split\): axis 1 of length 4 does not split into 3"):
        g3(torch.zeros(1, 4))


def test_sparse_to_dense_known_answer(tmp_path: Path) -> None:
    """No indices: every element the default (NanoDet's [0, 0, 0] added to a reshape target);
    N×rank indices take their values."""
    empty = {"name": "e", "op": "SparseToDense", "input": ["i0", "shape", "v0", "d"], "attr": {}}
    some = {"name": "f", "op": "SparseToDense", "input": ["i2", "shape2", "v2", "d"], "attr": {}}
    g = _graph(tmp_path, [empty, some], {
        "i0": np.zeros((0, 1), np.int32), "shape": np.array([3], np.int32), "v0": np.zeros((0,), np.int32),
        "d": np.array(7, np.int32), "i2": np.array([[0, 1], [1, 0]], np.int32),
        "shape2": np.array([2, 2], np.int32), "v2": np.array([5, 6], np.int32)}, ["e", "f"])
    out = g(torch.zeros(1))
    assert out["e"].tolist() == [7, 7, 7]
    assert out["f"].tolist() == [[7, 5], [6, 7]]


def test_outputs_of_another_shape_name_another_model(tmp_path: Path) -> None:
    relu = {"name": "y", "op": "Relu", "input": ["x"], "attr": {}}
    g = GraphModule(read_graph_model(write_model(tmp_path, [PLACEHOLDER, relu], {})), ["y"])
    check_outputs(g, torch.zeros(1, 4, 4, 3), {"y": (1, 4, 4, 3)}, "coco:m", "M", "m.json")
    with pytest.raises(VictimError, match=r"^victim 'coco:m': m\.json gives outputs \{'y': \(1, 4, 4, 3\)\}, "
                                          r"expected \{'y': \(1, 4, 4, 80\)\}: another model$"):
        check_outputs(g, torch.zeros(1, 4, 4, 3), {"y": (1, 4, 4, 80)}, "coco:m", "M", "m.json")
