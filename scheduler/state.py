"""Attack states in the store: scalars as JSON, tensors as array blobs.

An attack's state (:mod:`undream.attacks.base`) is a flat dict of tensors
(T0, the visibility mask, APGD's x_best, ...) and JSON values. The store
keeps the JSON values in the state document and each tensor as a
content-addressed ``.npy`` blob, so T0 is written once per run, not once per
iteration, and nothing is turned into float lists.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np


def encode_state(state: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``state`` as (plain JSON scalars, numpy arrays): what :meth:`Store.advance` takes."""
    import torch

    from undream.attacks import state_to_dict

    arrays = {k: v.detach().cpu().numpy() for k, v in state.items() if isinstance(v, torch.Tensor)}
    scalars = state_to_dict({k: v for k, v in state.items() if k not in arrays})
    return scalars, arrays


def decode_state(stored: Mapping[str, Any]) -> dict[str, Any]:
    """The attack state from what :meth:`Store.attack_state` returns (arrays back to tensors)."""
    import torch

    from undream.attacks import state_from_dict

    arrays = {k: torch.from_numpy(np.array(v)) for k, v in stored.items() if isinstance(v, np.ndarray)}
    return {**state_from_dict({k: v for k, v in stored.items() if k not in arrays}), **arrays}
