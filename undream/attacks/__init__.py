"""Attacks: registered, pure step functions on the texture, chosen by name.

Adding an attack is one class decorated with :func:`register`; switching is
``name`` in :class:`AttackConfig`. See :mod:`undream.attacks.base` for the
contract (units, visibility mask, non-finite gradients).

Imports are lazy so that reaching :class:`AttackConfig` (plain data, :mod:`undream.spec.attack`)
through this package loads no torch.
"""
from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "AttackConfig": "undream.spec.attack",
    "AttackError": "undream.errors",
    "Attack": "undream.attacks.base",
    "attack_names": "undream.attacks.base",
    "make_attack": "undream.attacks.base",
    "project_linf": "undream.attacks.base",
    "register": "undream.attacks.base",
    "apgd_checkpoints": "undream.attacks.apgd",
    "average_frames": "undream.attacks.minibatch",
    "frame_batch": "undream.attacks.minibatch",
    "state_from_dict": "undream.attacks.state",
    "state_to_dict": "undream.attacks.state",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'undream.attacks' has no attribute {name!r}")
