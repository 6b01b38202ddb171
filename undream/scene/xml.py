"""Mitsuba scene dictionaries, written as XML or loaded directly.

The scene adapter (:mod:`undream.scene.mitsuba_scene`) builds plain Mitsuba
dictionaries in which transforms are :class:`Mat4` / :class:`UVScale` markers
and colours are ``{'type': 'rgb', 'value': [...]}``. :func:`to_xml` writes
such a dictionary as a Mitsuba 3 XML file; :func:`to_mitsuba` turns the
markers into Mitsuba objects for ``mi.load_dict``.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any, Mapping
from xml.sax.saxutils import quoteattr

import numpy as np

# Keys whose dict value is an object reference rather than a plugin.
_REF = "ref"


@dataclass(frozen=True)
class Mat4:
    """A 4×4 transform (column-vector convention) in a scene dictionary."""

    m: tuple[float, ...]  # 16 numbers, row-major

    @classmethod
    def of(cls, array: Any) -> "Mat4":
        a = np.asarray(array, dtype=float).reshape(16)
        return cls(tuple(float(v) for v in a))


@dataclass(frozen=True)
class UVScale:
    """A texture's ``to_uv`` scale (texture repeats along u and v)."""

    u: float
    v: float


@dataclass(frozen=True)
class Default:
    """A ``$name`` parameter with a default, overridable at load time."""

    name: str
    value: int | float


def _num(v: float) -> str:
    return repr(float(v)) if not float(v).is_integer() else str(int(v)) if abs(v) < 1e15 else repr(v)


def _prop(key: str, value: Any, indent: str) -> list[str]:
    name = quoteattr(key)
    if isinstance(value, Mapping):
        if value.get("type") == "rgb":
            rgb = ", ".join(_num(x) for x in value["value"])
            return [f'{indent}<rgb name={name} value="{rgb}"/>']
        if value.get("type") == _REF:
            return [f'{indent}<ref name={name} id={quoteattr(value["id"])}/>']
        return _plugin(key, value, indent)
    if isinstance(value, Mat4):
        vals = " ".join(_num(x) for x in value.m)
        return [f'{indent}<transform name={name}>', f'{indent}    <matrix value="{vals}"/>',
                f'{indent}</transform>']
    if isinstance(value, UVScale):
        return [f'{indent}<transform name={name}>',
                f'{indent}    <scale x="{_num(value.u)}" y="{_num(value.v)}"/>', f'{indent}</transform>']
    if isinstance(value, Default):
        tag = "integer" if isinstance(value.value, int) else "float"
        return [f'{indent}<{tag} name={name} value="${value.name}"/>']
    if isinstance(value, bool):
        return [f'{indent}<boolean name={name} value="{str(value).lower()}"/>']
    if isinstance(value, int):
        return [f'{indent}<integer name={name} value="{value}"/>']
    if isinstance(value, float):
        return [f'{indent}<float name={name} value="{_num(value)}"/>']
    if isinstance(value, str):
        return [f'{indent}<string name={name} value={quoteattr(value)}/>']
    if isinstance(value, (list, tuple)) and len(value) == 3:
        return [f'{indent}<vector name={name} x="{_num(value[0])}" y="{_num(value[1])}" z="{_num(value[2])}"/>']
    raise TypeError(f"cannot write scene property {key!r} of type {type(value).__name__}")


_TAGS = {
    "integrator": "integrator", "sensor": "sensor", "film": "film", "sampler": "sampler",
    "rfilter": "rfilter", "emitter": "emitter", "bsdf": "bsdf", "texture": "texture",
    "medium": "medium", "shape": "shape", "phase": "phase",
}


def _category(value: Mapping[str, Any], key: str) -> str:
    t = value["type"]
    table = {
        "path": "integrator", "volpath": "integrator", "haze": "integrator", "prb": "integrator",
        "direct": "integrator", "aov": "integrator", "perspective": "sensor", "hdrfilm": "film", "independent": "sampler",
        "box": "rfilter", "gaussian": "rfilter", "tent": "rfilter",
        "constant": "emitter", "envmap": "emitter", "directional": "emitter", "point": "emitter", "area": "emitter",
        "spot": "emitter", "diffuse": "bsdf", "null": "bsdf", "twosided": "bsdf",
        "bitmap": "texture", "checkerboard": "texture", "homogeneous": "medium",
        "ply": "shape", "obj": "shape", "rectangle": "shape", "sphere": "shape", "cube": "shape",
        "cylinder": "shape", "disk": "shape", "isotropic": "phase",
    }
    if key in ("interior", "exterior", "medium") and t == "homogeneous":
        return "medium"
    if t not in table:
        raise TypeError(f"unknown plugin type {t!r} for key {key!r}")
    return table[t]


def _plugin(key: str, value: Mapping[str, Any], indent: str) -> list[str]:
    tag = _category(value, key)
    attrs = f' type={quoteattr(value["type"])}'
    if not key.startswith("_") and key not in ("sensor", "integrator") and tag in ("texture", "bsdf", "rfilter",
                                                                                  "film", "sampler", "phase"):
        attrs += f" name={quoteattr(key)}"
    if "id" in value:
        attrs += f" id={quoteattr(value['id'])}"
    lines = [f"{indent}<{tag}{attrs}>"]
    for k, v in value.items():
        if k in ("type", "id"):
            continue
        lines += _prop(k, v, indent + "    ")
    lines.append(f"{indent}</{tag}>")
    return lines


def to_xml(scene: Mapping[str, Any], defaults: Mapping[str, int | float] | None = None) -> str:
    """Serialise a scene dictionary (``{'type': 'scene', ...}``) as Mitsuba 3 XML.

    Top-level keys become object ids (``<shape id="object">``), so parameters
    appear under the same dotted keys in ``mi.traverse`` as with ``load_dict``.
    """
    lines = ['<scene version="3.0.0">']
    for name, value in (defaults or {}).items():
        lines.append(f'    <default name={quoteattr(name)} value="{value}"/>')
    for key, value in scene.items():
        if key == "type":
            continue
        node = dict(value)
        node.setdefault("id", key)
        lines += _plugin("_" + key, node, "    ")
    lines.append("</scene>")
    return "\n".join(lines) + "\n"


def to_mitsuba(value: Any, mi: ModuleType, params: Mapping[str, int | float] | None = None) -> Any:
    """Replace markers by Mitsuba objects so that ``mi.load_dict`` accepts the dict."""
    params = params or {}
    if isinstance(value, Mapping):
        return {k: to_mitsuba(v, mi, params) for k, v in value.items()}
    if isinstance(value, Mat4):
        return mi.ScalarTransform4f(np.array(value.m).reshape(4, 4).tolist())
    if isinstance(value, UVScale):
        return mi.ScalarTransform3f.scale([value.u, value.v])
    if isinstance(value, Default):
        return params.get(value.name, value.value)
    return value
