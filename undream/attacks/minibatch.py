"""Frame minibatches and their average: which frames an iteration uses, and the mean over them.

Each iteration averages the loss and the texture gradient over its frames:
all of them, or a minibatch drawn from the run's seed and the iteration
number only, so that a retried or resumed iteration draws the same frames.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
import torch

from undream.errors import AttackError


def frame_batch(n_frames: int, batch_size: int | None, iteration: int, seed: int) -> list[int]:
    """Sorted frame indices for ``iteration``: all frames when ``batch_size`` is
    None or ``>= n_frames``, else ``batch_size`` distinct ones drawn from
    ``(seed, iteration)``."""
    for field, value, least in (("n_frames", n_frames, 1), ("iteration", iteration, 0),
                                ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            raise AttackError(f"frame_batch: {field} must be an integer >= {least}, got {value!r}")
    if batch_size is not None and (isinstance(batch_size, bool) or not isinstance(batch_size, int)
                                   or batch_size < 1):
        raise AttackError(f"frame_batch: batch_size must be None or an integer >= 1, "
                          f"got {batch_size!r}")
    if batch_size is None or batch_size >= n_frames:
        return list(range(n_frames))
    rng = np.random.default_rng([seed, iteration])
    return sorted(int(i) for i in rng.choice(n_frames, size=batch_size, replace=False))


def average_frames(grads: Sequence[torch.Tensor], losses: Sequence[Any],
                   finite: Sequence[bool] | None = None, *,
                   weights: str = "mean") -> tuple[torch.Tensor, float, list[int]]:
    """Mean gradient and mean loss over the frames whose gradient and loss are
    finite, and the positions of those frames. No finite frame: AttackError.

    ``weights`` (``attack.frame_weights``): ``mean``, the plain mean; ``unit``, each kept frame's
    gradient first scaled to the kept frames' mean L2 norm (a zero gradient stays zero), so every
    frame that sees the texture steers the step's direction alike while its size stays the mean's.

    ``finite``: one flag per frame, False for a frame known to be bad although
    its gradient looks finite (a NaN in the victim's image gradient that the
    renderer's backward pass turned into a finite texture gradient); None: all True.
    """
    if len(grads) != len(losses) or not grads or (finite is not None and len(finite) != len(grads)):
        raise AttackError(f"average_frames: need one loss (and finiteness flag) per gradient and at "
                          f"least one frame, got {len(grads)} gradients and {len(losses)} losses")
    values = [float(v) for v in losses]
    flags = [True] * len(grads) if finite is None else [bool(f) for f in finite]
    stacked = torch.stack(list(grads))
    finite_grads = torch.isfinite(stacked).flatten(1).all(dim=1).tolist()  # one pass over every frame
    kept = [i for i, (v, ok, g_ok) in enumerate(zip(values, flags, finite_grads))
            if ok and math.isfinite(v) and g_ok]
    if not kept:
        raise AttackError(f"average_frames: all {len(grads)} frames have a non-finite "
                          "gradient or loss")
    chosen = stacked if len(kept) == len(grads) else stacked[kept]
    if weights == "unit":
        norms = chosen.flatten(1).norm(dim=1)
        scale = torch.where(norms > 0, norms.mean() / norms.clamp_min(torch.finfo(norms.dtype).tiny), 0.0)
        chosen = chosen * scale.view(-1, *([1] * (chosen.dim() - 1)))
    elif weights != "mean":
        raise AttackError(f"average_frames: weights must be 'mean' or 'unit', got {weights!r}")
    G = chosen.mean(dim=0)
    return G, sum(values[i] for i in kept) / len(kept), kept
