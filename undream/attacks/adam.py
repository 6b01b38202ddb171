"""Adam ascent on the texture, projected (Kingma & Ba 2015).

The unbounded variant is ``eps >= 255``: only the [0, 1] box remains. With a
smaller ``eps`` Adam is projected onto the ε ball like every attack, so that
switching attacks never silently drops the budget. The update follows
``torch.optim.Adam(maximize=True)`` (β = 0.9, 0.999; ε_Adam = 1e-8), then
projects; ``lr`` is in 0–255 units.
"""
from __future__ import annotations

import math

import torch

from undream.attacks.base import Attack, State, project_linf, register

BETA1, BETA2, ADAM_EPS = 0.9, 0.999, 1e-8


def adam_step(T: torch.Tensor, G: torch.Tensor, m: torch.Tensor, v: torch.Tensor, t: int,
              T0: torch.Tensor, eps: float,
              lr: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step number ``t`` (1-based) of Adam ascent: new texture, m and v (lr in 0–1 units)."""
    m = torch.lerp(m, G, 1 - BETA1)
    v = torch.addcmul(v * BETA2, G, G, value=1 - BETA2)
    denom = v.sqrt() / math.sqrt(1 - BETA2 ** t) + ADAM_EPS
    step = lr / (1 - BETA1 ** t)
    return project_linf(torch.addcdiv(T, m, denom, value=step), T0, eps), m, v


@register
class Adam(Attack):
    """Adam with learning rate ``config.lr`` (0–255 units)."""

    name = "adam"

    def _init_state(self, T: torch.Tensor) -> State:
        return {"m": torch.zeros_like(T), "v": torch.zeros_like(T), "t": 0}

    def _step(self, T: torch.Tensor, G: torch.Tensor, loss: float,
              state: State) -> tuple[torch.Tensor, State]:
        t = state["t"] + 1
        T_next, m, v = adam_step(T, G, state["m"], state["v"], t, state["T0"], self.eps,
                                 self.config.lr / 255.0)
        return T_next, {"m": m, "v": v, "t": t}
