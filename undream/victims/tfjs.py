"""Reading a TensorFlow.js graph model (``model.json`` + weight shards) into torch.

A TF.js graph model is a frozen TensorFlow graph: ``model.json`` holds the
nodes (``modelTopology.node``: name, op, inputs, attributes) and the weights
manifest (which shard files hold which constant, with its dtype, shape and
quantisation); the shards are raw little-endian bytes. tf2onnx and onnx2torch
need a TensorFlow SavedModel, not this format, so undream reads the graph
itself and runs it op by op in torch (:class:`GraphModule`), differentiably.

Tensors keep the graph's own layout: images are ``N×H×W×C`` (NHWC) for most
graphs, ``N×C×H×W`` for ONNX conversions (NanoDet), whose explicit Transpose
nodes bring them to NHWC around each convolution; convolutions run on a
channels-last view, so no copy is made.
Supported ops: :data:`OPS`. An op outside it, a weight file of another size
than its manifest says, or a constant with no weight is one
:class:`~undream.errors.VictimError` line naming it, raised when the module is
built (before anything runs).
"""
from __future__ import annotations

import base64
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from undream.errors import VictimError

DTYPES = {"float32": np.dtype("<f4"), "int32": np.dtype("<i4"), "bool": np.dtype("bool")}
QUANTIZED = {"float16": np.dtype("<f2"), "uint8": np.dtype("u1"), "uint16": np.dtype("<u2")}
TORCH_DTYPES = {"DT_FLOAT": torch.float32, "DT_INT32": torch.int32, "DT_BOOL": torch.bool,
                "DT_INT64": torch.int64}
FUSED_ACTIVATIONS = {"Relu": F.relu, "Relu6": lambda x: x.clamp(0.0, 6.0), "Sigmoid": torch.sigmoid,
                     "Elu": F.elu, "Tanh": torch.tanh}


@dataclass(frozen=True)
class Node:
    """One graph node: ``name``, ``op``, its ``inputs`` as ``(node, output index)``
    pairs (control inputs, ``^name``, dropped) and its raw ``attr`` dict."""

    name: str
    op: str
    inputs: tuple[tuple[str, int], ...]
    attr: dict[str, Any]

    def get(self, key: str, default: Any = None) -> Any:
        """The attribute ``key`` decoded from TF.js's JSON (strings base64, ints as text)."""
        return decode_attr(self.attr[key]) if key in self.attr else default


@dataclass(frozen=True)
class GraphModel:
    """A parsed TF.js graph model: ``nodes`` by name (file order), ``weights`` by
    constant name (numpy arrays), the signature's ``inputs`` and ``outputs``
    (name → shape, ``-1`` where unknown) and ``source`` (the model.json path)."""

    nodes: dict[str, Node]
    weights: dict[str, np.ndarray]
    inputs: dict[str, tuple[int, ...]]
    outputs: dict[str, tuple[int, ...]]
    source: str


def decode_attr(value: dict[str, Any]) -> Any:
    """One attribute value of TF.js's JSON as a Python value."""
    if "list" in value:
        lst = value["list"]
        if "i" in lst:
            return [int(v) for v in lst["i"]]
        if "s" in lst:
            return [base64.b64decode(v).decode() for v in lst["s"]]
        if "f" in lst:
            return [float(v) for v in lst["f"]]
        return []
    for key, conv in (("s", lambda v: base64.b64decode(v).decode()), ("i", int), ("f", float),
                      ("b", bool), ("type", str)):
        if key in value:
            return conv(value[key])
    if "shape" in value:
        return tuple(int(d.get("size", -1)) for d in value["shape"].get("dim", []))
    return value


def _split_input(text: str) -> tuple[str, int] | None:
    if text.startswith("^"):
        return None
    name, _, index = text.partition(":")
    return name, int(index) if index else 0


def read_graph_model(path: str | Path) -> GraphModel:
    """Parse ``model.json`` (or the folder holding it) and its weight shards.

    One-line :class:`VictimError` for a file that is not a TF.js graph model,
    a missing shard, or shards whose size differs from what the manifest says.
    """
    p = Path(path)
    p = p / "model.json" if p.is_dir() else p
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
        topology, manifest = doc["modelTopology"], doc["weightsManifest"]
        raw_nodes = topology["node"]
    except (OSError, ValueError) as err:
        raise VictimError(f"TF.js model {str(p)!r}: cannot read it ({err})") from None
    except (KeyError, TypeError):
        raise VictimError(f"TF.js model {str(p)!r}: not a TF.js graph model (expected modelTopology.node "
                          f"and weightsManifest)") from None
    nodes = {}
    for n in raw_nodes:
        ins = tuple(x for x in (_split_input(i) for i in n.get("input", [])) if x is not None)
        nodes[n["name"]] = Node(n["name"], n["op"], ins, n.get("attr", {}))
    sig = doc.get("signature") or {}
    return GraphModel(nodes, _read_weights(p, manifest), _signature(sig.get("inputs")),
                      _signature(sig.get("outputs")), str(p))


def _signature(entries: dict[str, Any] | None) -> dict[str, tuple[int, ...]]:
    out = {}
    for key, spec in (entries or {}).items():
        dims = spec.get("tensorShape", {}).get("dim", [])
        out[spec.get("name", key)] = tuple(int(d.get("size", -1)) for d in dims)
    return out


def _read_weights(model_json: Path, manifest: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    weights: dict[str, np.ndarray] = {}
    for group in manifest:
        files = [model_json.parent / f for f in group["paths"]]
        try:
            data = b"".join(f.read_bytes() for f in files)
        except OSError as err:
            raise VictimError(f"TF.js model {str(model_json)!r}: cannot read weight shard ({err})") from None
        offset = 0
        for spec in group["weights"]:
            arr, used = _one_weight(spec, data, offset, files)
            weights[spec["name"]] = arr
            offset += used
        if offset != len(data):
            raise VictimError(f"TF.js model {str(model_json)!r}: weight files {[f.name for f in files]} hold "
                              f"{len(data)} bytes, the manifest's shapes need {offset}: weights of "
                              f"another shape or another model")
    return weights


def _one_weight(spec: dict[str, Any], data: bytes, offset: int, files: Sequence[Path]) -> tuple[np.ndarray, int]:
    """One manifest entry's array (dequantised to its dtype) and the bytes it takes."""
    shape = tuple(int(s) for s in spec["shape"])
    count = math.prod(shape)
    quant = spec.get("quantization")
    dtype = DTYPES.get(spec["dtype"])
    stored = QUANTIZED.get(quant["dtype"]) if quant else dtype
    if dtype is None or stored is None:
        raise VictimError(f"TF.js weight {spec['name']!r}: dtype {spec['dtype']!r}"
                          f"{' quantised as ' + repr(quant['dtype']) if quant else ''} is not supported "
                          f"(supported: {', '.join(DTYPES)}; quantised {', '.join(QUANTIZED)})")
    size = count * stored.itemsize
    if offset + size > len(data):
        raise VictimError(f"TF.js weight {spec['name']!r}: needs bytes {offset}..{offset + size} but the "
                          f"weight files {[f.name for f in files]} hold {len(data)}: weights of another shape")
    arr = np.frombuffer(data, stored, count, offset).reshape(shape)
    if quant and quant["dtype"] != "float16":
        arr = arr.astype(np.float32) * float(quant["scale"]) + float(quant["min"])
    return arr.astype(dtype), size


# --------------------------------------------------------------------------- ops

Op = Callable[["GraphModule", Node, list[Any]], Any]


def _pads_same(size: int, k: int, stride: int, dilation: int) -> tuple[int, int]:
    """TensorFlow's SAME padding of one axis: (before, after); the odd pixel goes after."""
    eff = (k - 1) * dilation + 1
    total = max((math.ceil(size / stride) - 1) * stride + eff - size, 0)
    return total // 2, total - total // 2


def _padded(node: Node, x: torch.Tensor, kh: int, kw: int, strides: Sequence[int],
            dilations: Sequence[int], value: float = 0.0) -> torch.Tensor:
    """``x`` (NCHW) padded as the node's ``padding`` attribute says."""
    padding = node.get("padding")
    if padding == "VALID":
        return x
    if padding == "SAME":
        top, bottom = _pads_same(x.shape[2], kh, strides[0], dilations[0])
        left, right = _pads_same(x.shape[3], kw, strides[1], dilations[1])
    elif padding == "EXPLICIT":
        p = node.get("explicit_paddings")
        top, bottom, left, right = p[2], p[3], p[4], p[5]
    else:
        raise VictimError(f"TF.js node {node.name!r} ({node.op}): padding {padding!r} is not supported")
    if top == bottom == left == right == 0:
        return x
    return F.pad(x, (left, right, top, bottom), value=value)


def _nhwc_attr(node: Node, key: str, default: Sequence[int]) -> tuple[int, int]:
    if node.get("data_format", "NHWC") != "NHWC":
        raise VictimError(f"TF.js node {node.name!r} ({node.op}): data_format "
                          f"{node.get('data_format')!r} is not supported (only NHWC)")
    v = node.get(key, list(default))
    return int(v[1]), int(v[2])


def _conv(g: "GraphModule", node: Node, args: list[Any], depthwise: bool) -> torch.Tensor:
    x, w = args[0], g.prepared(node, args[1], depthwise)
    strides, dilations = _nhwc_attr(node, "strides", (1, 1, 1, 1)), _nhwc_attr(node, "dilations", (1, 1, 1, 1))
    xc = _padded(node, x.permute(0, 3, 1, 2), w.shape[2], w.shape[3], strides, dilations)
    y = F.conv2d(xc, w, None, strides, 0, dilations, groups=x.shape[-1] if depthwise else 1)
    y = y.permute(0, 2, 3, 1)
    return _fused(node, y, args[2:])


def _fused(node: Node, y: torch.Tensor, extra: list[Any]) -> torch.Tensor:
    ops = node.get("fused_ops", [])
    if not ops:
        return y
    if ops[0] != "BiasAdd":
        raise VictimError(f"TF.js node {node.name!r} ({node.op}): fused ops {ops} are not supported "
                          f"(the first must be BiasAdd)")
    y = y + extra[0]
    for name in ops[1:]:
        if name == "LeakyRelu":
            y = F.leaky_relu(y, node.get("leakyrelu_alpha", 0.2))
        elif name == "Prelu":
            y = torch.where(y >= 0, y, y * extra[1])
        elif name in FUSED_ACTIVATIONS:
            y = FUSED_ACTIVATIONS[name](y)
        else:
            raise VictimError(f"TF.js node {node.name!r} ({node.op}): fused activation {name!r} is not "
                              f"supported (supported: {', '.join([*FUSED_ACTIVATIONS, 'LeakyRelu', 'Prelu'])})")
    return y


def _max_pool(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    kh, kw = _nhwc_attr(node, "ksize", (1, 1, 1, 1))
    strides = _nhwc_attr(node, "strides", (1, 1, 1, 1))
    x = _padded(node, args[0].permute(0, 3, 1, 2), kh, kw, strides, (1, 1), value=-math.inf)
    return F.max_pool2d(x, (kh, kw), strides).permute(0, 2, 3, 1)


def _source_index(out: int, size: int, align: bool, half: bool, device: torch.device
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """TensorFlow's bilinear source positions for ``out`` outputs from ``size``
    inputs: lower index, upper index and the weight of the upper one."""
    dst = torch.arange(out, dtype=torch.float32, device=device)
    if align and out > 1:
        src = dst * ((size - 1) / (out - 1))
    elif half:
        src = ((dst + 0.5) * (size / out) - 0.5).clamp(min=0.0)
    else:
        src = dst * (size / out)
    lo = src.floor().clamp(max=size - 1)
    hi = (lo + 1).clamp(max=size - 1)
    return lo.long(), hi.long(), (src - lo).clamp(0.0, 1.0)


def _resize_bilinear(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    x, size = args[0], [v * g.resize_scale for v in args[1].tolist()]
    if any(v != int(v) or v < 1 for v in size):
        raise VictimError(f"TF.js node {node.name!r} (ResizeBilinear): size {args[1].tolist()} × "
                          f"{g.resize_scale} is not a whole number of pixels")
    size = [int(v) for v in size]
    align, half = bool(node.get("align_corners", False)), bool(node.get("half_pixel_centers", False))
    lo, hi, t = _source_index(size[0], x.shape[1], align, half, x.device)
    x = x[:, lo] * (1 - t)[None, :, None, None] + x[:, hi] * t[None, :, None, None]
    lo, hi, t = _source_index(size[1], x.shape[2], align, half, x.device)
    return x[:, :, lo] * (1 - t)[None, None, :, None] + x[:, :, hi] * t[None, None, :, None]


def _strided_slice(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    x, begin, end, strides = args[0], args[1].tolist(), args[2].tolist(), args[3].tolist()
    for mask in ("ellipsis_mask", "new_axis_mask"):
        if node.get(mask, 0):
            raise VictimError(f"TF.js node {node.name!r} (StridedSlice): {mask} is not supported")
    bm, em, sm = node.get("begin_mask", 0), node.get("end_mask", 0), node.get("shrink_axis_mask", 0)
    index: list[Any] = []
    for axis, (b, e, s) in enumerate(zip(begin, end, strides)):
        if sm >> axis & 1:
            index.append(int(b))
            continue
        index.append(slice(None if bm >> axis & 1 else int(b), None if em >> axis & 1 else int(e), int(s)))
    return x[tuple(index)]


def _gather(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    params, indices, axis = args[0], args[1].long(), int(args[2])
    if node.get("batch_dims", 0):
        raise VictimError(f"TF.js node {node.name!r} (GatherV2): batch_dims is not supported")
    axis = axis % params.ndim
    flat = params.index_select(axis, indices.reshape(-1))
    return flat.reshape(*params.shape[:axis], *indices.shape, *params.shape[axis + 1:])


def _top_k(g: "GraphModule", node: Node, args: list[Any]) -> tuple[torch.Tensor, torch.Tensor]:
    values, indices = torch.topk(args[0], int(args[1]), dim=-1, sorted=True)
    return values, indices.int()


def _pad(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    """Pad / PadV2: ``args[1]`` is ``rank×2`` (before, after) per axis; the value is
    ``args[2]`` (PadV2, e.g. -inf before a max pool) or 0."""
    pairs = [[int(v) for v in pair] for pair in args[1].tolist()]
    if len(pairs) != args[0].ndim or any(v < 0 for pair in pairs for v in pair):
        raise VictimError(f"TF.js node {node.name!r} ({node.op}): paddings {pairs} do not fit a tensor of "
                          f"shape {tuple(args[0].shape)} (one non-negative (before, after) pair per axis)")
    value = float(args[2]) if len(args) > 2 else 0.0
    return F.pad(args[0], [v for pair in reversed(pairs) for v in pair], value=value)


def _split_v(g: "GraphModule", node: Node, args: list[Any]) -> tuple[torch.Tensor, ...]:
    """SplitV: ``x`` cut along ``args[2]`` into pieces of the sizes ``args[1]`` (one may
    be -1: the rest); a tuple, one output per piece (``name:i``)."""
    x, sizes = args[0], [int(s) for s in args[1].reshape(-1).tolist()]
    axis = int(args[2]) % x.ndim
    if sizes.count(-1) == 1:
        sizes[sizes.index(-1)] = x.shape[axis] - sum(sizes) - 1
    if sum(sizes) != x.shape[axis] or min(sizes) < 0:
        raise VictimError(f"TF.js node {node.name!r} (SplitV): sizes {sizes} do not split axis {axis} of "
                          f"length {x.shape[axis]}")
    return tuple(torch.split(x, sizes, axis))


def _split(g: "GraphModule", node: Node, args: list[Any]) -> tuple[torch.Tensor, ...]:
    """Split: ``args[1]`` cut along axis ``args[0]`` into ``num_split`` equal pieces (a tuple)."""
    x, n = args[1], int(node.get("num_split", 1))
    axis = int(args[0]) % x.ndim
    if n < 1 or x.shape[axis] % n:
        raise VictimError(f"TF.js node {node.name!r} (Split): axis {axis} of length {x.shape[axis]} does not "
                          f"split into {n} equal pieces")
    return tuple(torch.split(x, x.shape[axis] // n, axis))


def _sparse_to_dense(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    """SparseToDense: a tensor of shape ``args[1]`` holding ``args[3]`` (the default)
    except at ``args[0]`` (``N×rank``, ``N`` or a scalar index), which take ``args[2]``
    (one value per index, or one for all)."""
    indices, values, default = args[0].long(), args[2], args[3]
    shape = [int(s) for s in args[1].reshape(-1).tolist()]
    indices = indices.reshape(-1, 1) if indices.ndim < 2 else indices
    if indices.shape[1] != len(shape):
        raise VictimError(f"TF.js node {node.name!r} (SparseToDense): indices of shape {tuple(indices.shape)} "
                          f"do not index an output of shape {shape}")
    out = default.to(values.dtype).expand(shape).clone()
    return out.index_put(tuple(indices.t()), values.expand(indices.shape[0]))


def _cast(g: "GraphModule", node: Node, args: list[Any]) -> torch.Tensor:
    dst = node.get("DstT")
    if dst not in TORCH_DTYPES:
        raise VictimError(f"TF.js node {node.name!r} (Cast): DstT {dst!r} is not supported")
    return args[0].to(TORCH_DTYPES[dst])


def _binary(fn: Callable[[Any, Any], Any]) -> Op:
    return lambda g, node, args: fn(args[0], args[1])


def _unary(fn: Callable[[Any], Any]) -> Op:
    return lambda g, node, args: fn(args[0])


OPS: dict[str, Op] = {
    "Identity": _unary(lambda x: x),
    "Add": _binary(torch.add), "AddV2": _binary(torch.add), "Sub": _binary(torch.sub),
    "Mul": _binary(torch.mul), "RealDiv": _binary(torch.div), "Maximum": _binary(torch.maximum),
    "Minimum": _binary(torch.minimum), "Equal": _binary(torch.eq),
    "FloorDiv": _binary(lambda a, b: torch.div(a, b, rounding_mode="floor")),
    "FloorMod": _binary(torch.remainder),
    "Relu": _unary(F.relu), "Relu6": _unary(lambda x: x.clamp(0.0, 6.0)), "Sigmoid": _unary(torch.sigmoid),
    "Tanh": _unary(torch.tanh), "Elu": _unary(F.elu),
    "LeakyRelu": lambda g, node, args: F.leaky_relu(args[0], node.get("alpha", 0.2)),
    "Conv2D": lambda g, node, args: _conv(g, node, args, False),
    "_FusedConv2D": lambda g, node, args: _conv(g, node, args, False),
    "DepthwiseConv2dNative": lambda g, node, args: _conv(g, node, args, True),
    "FusedDepthwiseConv2dNative": lambda g, node, args: _conv(g, node, args, True),
    "MaxPool": _max_pool,
    "Mean": lambda g, node, args: args[0].mean([int(a) for a in args[1].reshape(-1).tolist()],
                                               keepdim=bool(node.get("keep_dims", False))),
    "ConcatV2": lambda g, node, args: torch.cat(args[:-1], int(args[-1])),
    "ResizeBilinear": _resize_bilinear,
    "Reshape": lambda g, node, args: args[0].reshape([int(v) for v in args[1].tolist()]),
    "Transpose": lambda g, node, args: args[0].permute([int(v) for v in args[1].tolist()]),
    "Pad": _pad, "PadV2": _pad,
    "SplitV": _split_v, "Split": _split,
    "SparseToDense": _sparse_to_dense,
    "ExpandDims": lambda g, node, args: args[0].unsqueeze(int(args[1])),
    "Cast": _cast,
    "StridedSlice": _strided_slice,
    "GatherV2": _gather,
    "TopKV2": _top_k,
}
SOURCES = ("Placeholder", "Const")


class GraphModule(nn.Module):
    """A TF.js graph as a torch module computing ``outputs`` from its one input.

    ``forward(x)``: ``x`` in the graph's layout (images ``N×H×W×C``, or ``N×C×H×W``
    where the graph's signature says so; float32) →
    a dict output name → tensor. Constants are buffers (``.to(device)`` moves
    them); convolution filters are kept in torch's layout. Every op needed for
    ``outputs`` is checked against :data:`OPS` here, before anything runs.
    ``resize_scale``: the graph fed images this many times the size it was
    converted for; a ``ResizeBilinear`` whose size the converter folded into a
    constant (an upsampling by 2 written as the converted size) resizes to that
    constant × ``resize_scale``.
    """

    def __init__(self, model: GraphModel, outputs: Sequence[str], input_name: str | None = None,
                 resize_scale: float = 1.0) -> None:
        super().__init__()
        self.resize_scale = float(resize_scale)
        placeholders = [n.name for n in model.nodes.values() if n.op == "Placeholder"]
        self.input_name = input_name or (placeholders[0] if len(placeholders) == 1 else "")
        if self.input_name not in placeholders:
            raise VictimError(f"TF.js model {model.source!r}: input {self.input_name!r} is not one of its "
                              f"placeholders {placeholders}")
        self.output_names = list(outputs)
        self.order = _schedule(model, self.output_names)
        self.nodes = {n: model.nodes[n] for n in self.order}
        self.const_keys: dict[str, str] = {}
        for i, name in enumerate(n for n in self.order if model.nodes[n].op == "Const"):
            if name not in model.weights:
                raise VictimError(f"TF.js model {model.source!r}: constant {name!r} has no weight in the manifest")
            key = f"const{i}"
            self.register_buffer(key, torch.from_numpy(model.weights[name].copy()), persistent=False)
            self.const_keys[name] = key
        self._prepared: dict[str, torch.Tensor] = {}

    def prepared(self, node: Node, w: torch.Tensor, depthwise: bool) -> torch.Tensor:
        """The filter ``w`` (TF's ``H×W×In×Out``, or ``H×W×C×M`` depthwise) in torch's
        ``Out×In×H×W`` layout, converted once per node and device."""
        key = f"{node.name}@{w.device}"
        got = self._prepared.get(key)
        if got is None:
            if depthwise:
                h, k, c, m = w.shape
                got = w.permute(2, 3, 0, 1).reshape(c * m, 1, h, k).contiguous()
            else:
                got = w.permute(3, 2, 0, 1).contiguous()
            self._prepared[key] = got
        return got

    def _apply(self, fn: Any, recurse: bool = True) -> "GraphModule":  # .to()/.cuda() drop prepared filters
        self._prepared = {}
        return super()._apply(fn, recurse)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        values: dict[str, Any] = {}
        for name in self.order:
            node = self.nodes[name]
            if node.op == "Placeholder":
                values[name] = x
            elif node.op == "Const":
                values[name] = getattr(self, self.const_keys[name])
            else:
                args = [_output(values[i], k) for i, k in node.inputs]
                values[name] = OPS[node.op](self, node, args)
        return {o: _output(values[o.partition(":")[0]], int(o.partition(":")[2] or 0)) for o in self.output_names}


def check_outputs(graph: GraphModule, x: torch.Tensor, want: dict[str, tuple[int, ...]], victim: str,
                  model: str, where: str) -> None:
    """Run ``graph`` once on ``x`` (zeros of its input's shape): its outputs must have the shapes
    ``want`` (output name → shape); else one :class:`VictimError` line saying that ``where`` (the
    file of ``victim``) does not hold ``model``: weights of another shape or another model."""
    try:
        with torch.no_grad():
            out = graph(x)
    except (RuntimeError, IndexError, ValueError) as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise VictimError(f"victim {victim!r}: {where} does not run as {model} ({first}): weights of another "
                          f"shape or another model") from None
    got = {k: tuple(v.shape) for k, v in out.items()}
    if got != want:
        raise VictimError(f"victim {victim!r}: {where} gives outputs {got}, expected {want}: another model")


def _output(value: Any, index: int) -> Any:
    return value[index] if isinstance(value, tuple) else value


def _schedule(model: GraphModel, outputs: Sequence[str]) -> list[str]:
    """The nodes that ``outputs`` need, each after its inputs; unknown ops and
    names are one-line errors."""
    order: list[str] = []
    state: dict[str, int] = {}
    for out in outputs:
        root = out.partition(":")[0]
        if root not in model.nodes:
            raise VictimError(f"TF.js model {model.source!r}: no node named {root!r} (outputs: "
                              f"{', '.join(model.outputs) or 'none declared'})")
        stack = [(root, False)]
        while stack:
            name, done = stack.pop()
            if done:
                state[name] = 2
                order.append(name)
                continue
            if state.get(name):
                continue
            node = model.nodes.get(name)
            if node is None:
                raise VictimError(f"TF.js model {model.source!r}: node input {name!r} does not exist")
            if node.op not in OPS and node.op not in SOURCES:
                raise VictimError(f"TF.js model {model.source!r}: op {node.op!r} (node {name!r}) is not "
                                  f"supported by undream's TF.js loader (supported: {', '.join(sorted(OPS))})")
            state[name] = 1
            stack.append((name, True))
            stack.extend((i, False) for i, _ in reversed(node.inputs) if not state.get(i))
    return order
