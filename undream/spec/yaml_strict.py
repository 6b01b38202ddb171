"""YAML as undream reads it: safe types only, and nothing that a typo or a hostile file can abuse.

:func:`load` composes the document first and checks the node graph before any
Python object is built, against :data:`undream.spec.limits.FILE_LIMITS`:

- nesting deeper than ``depth`` is refused while composing (no recursion error);
- an alias inside the value it names (``&a [*a]``) is refused;
- a document of more than ``nodes`` values once its aliases are expanded (a
  "billion laughs") is refused, counted without expanding it;
- a key given twice in one mapping is refused, naming both lines (the last
  one no longer wins silently);
- a number of more than ``digits`` digits is refused, naming its field.

Errors are :class:`SpecError` lines without the file name (the reader adds it).
"""
from __future__ import annotations

from typing import Any

import yaml
from yaml.events import AliasEvent, CollectionStartEvent
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from undream.errors import SpecError
from undream.spec.limits import FILE_LIMITS

_NUMBER_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")


class _Loader(yaml.SafeLoader):
    """A safe loader that refuses deep nesting and self-referencing aliases while composing."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._open: list[str | None] = []  # anchors of the collections being composed

    def compose_node(self, parent: Node | None, index: Any) -> Node:
        event = self.peek_event()
        line = event.start_mark.line + 1
        if isinstance(event, AliasEvent) and event.anchor in self._open:
            raise SpecError(f"line {line}: alias *{event.anchor} is inside the value it names")
        self._depth += 1
        if self._depth > FILE_LIMITS["depth"]:
            raise SpecError(f"line {line}: nested deeper than {FILE_LIMITS['depth']} levels")
        self._open.append(event.anchor if isinstance(event, CollectionStartEvent) else None)
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1
            self._open.pop()


def _expanded(node: Node, sizes: dict[int, int]) -> int:
    """How many values ``node`` stands for once every alias is expanded (memoised per node)."""
    if id(node) not in sizes:
        children: list[Node] = []
        if isinstance(node, SequenceNode):
            children = node.value
        elif isinstance(node, MappingNode):
            children = [n for pair in node.value for n in pair]
        total = 1
        for child in children:
            total += _expanded(child, sizes)
            if total > FILE_LIMITS["nodes"]:
                break
        sizes[id(node)] = total
    return sizes[id(node)]


def _check(node: Node, field: str, seen: set[int]) -> None:
    """Duplicate keys and over-long numbers under ``node`` (each node checked once)."""
    if id(node) in seen:
        return
    seen.add(id(node))
    if isinstance(node, ScalarNode):
        digits = sum(ch.isdigit() for ch in node.value)
        if node.tag in _NUMBER_TAGS and digits > FILE_LIMITS["digits"]:
            raise SpecError(f"{field or 'value'}: a number of {digits} digits is not a number in range "
                            f"(line {node.start_mark.line + 1}; at most {FILE_LIMITS['digits']} digits)")
    elif isinstance(node, SequenceNode):
        for i, child in enumerate(node.value):
            _check(child, f"{field}[{i}]", seen)
    elif isinstance(node, MappingNode):
        first: dict[str, int] = {}
        for key, value in node.value:
            name = key.value if isinstance(key, ScalarNode) else "?"
            line = key.start_mark.line + 1
            if isinstance(key, ScalarNode) and name != "<<":
                if name in first:
                    raise SpecError(f"line {line}: duplicate key {name!r} (first at line {first[name]}); "
                                    "give each key once")
                first[name] = line
            _check(value, f"{field}.{name}" if field else str(name), seen)


def load(text: str) -> Any:
    """The document in ``text`` as plain Python data (None for an empty one); see the module docstring."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded(node, {}) > FILE_LIMITS["nodes"]:
            raise SpecError(f"more than {FILE_LIMITS['nodes']} values once its aliases are expanded "
                            "(an alias bomb?)")
        _check(node, "", set())
        return loader.construct_document(node)
    finally:
        loader.dispose()
