"""MI-FGSM: momentum iterative sign-gradient ascent (Dong et al., CVPR 2018).

``g_{k+1} = μ·g_k + G_k / ‖G_k‖₁`` and ``T_{k+1} = P(T_k + α·sign(g_{k+1}))``,
the L1 norm over the whole texture (an all-zero gradient adds nothing).
"""
from __future__ import annotations

import torch

from undream.attacks.base import Attack, State, decayed_step, project_linf, register

_TINY = 1e-12


def mifgsm_step(T: torch.Tensor, G: torch.Tensor, g: torch.Tensor, T0: torch.Tensor,
                eps: float, step_size: float,
                momentum: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One MI-FGSM step: the new texture and the new accumulated gradient."""
    g_next = momentum * g + G / G.abs().sum().clamp_min(_TINY)
    return project_linf(T + step_size * torch.sign(g_next), T0, eps), g_next


@register
class MIFGSM(Attack):
    """MI-FGSM with decay ``config.momentum``; ``step_size`` defaults to ``eps/steps``."""

    name = "mifgsm"

    @property
    def step_size(self) -> float:
        """Sign-step size in 0–1 units."""
        c = self.config
        return (c.step_size if c.step_size is not None else c.eps / c.steps) / 255.0

    def _init_state(self, T: torch.Tensor) -> State:
        return {"g": torch.zeros_like(T)}

    def _step(self, T: torch.Tensor, G: torch.Tensor, loss: float,
              state: State) -> tuple[torch.Tensor, State]:
        size = decayed_step(self.step_size, state["iteration"], self.config.steps, self.config.step_decay)
        T_next, g = mifgsm_step(T, G, state["g"], state["T0"], self.eps, size, self.config.momentum)
        return T_next, {"g": g}
