"""PGD: projected L∞ sign-gradient ascent (Madry et al. 2018).

``T_{k+1} = P(T_k + α·sign(G_k))`` with ``P`` the projection onto the ε ball
around the starting texture and onto [0, 1]; optional uniform random start.
"""
from __future__ import annotations

import torch

from undream.attacks.base import Attack, State, decayed_step, project_linf, register


def pgd_step(T: torch.Tensor, G: torch.Tensor, T0: torch.Tensor, eps: float,
             step_size: float) -> torch.Tensor:
    """One PGD step; ``eps`` and ``step_size`` in 0–1 units."""
    return project_linf(T + step_size * torch.sign(G), T0, eps)


@register
class PGD(Attack):
    """L∞ PGD; ``step_size`` defaults to ``2.5·eps/steps``."""

    name = "pgd"

    @property
    def step_size(self) -> float:
        """Sign-step size in 0–1 units."""
        c = self.config
        return (c.step_size if c.step_size is not None else 2.5 * c.eps / c.steps) / 255.0

    def _step(self, T: torch.Tensor, G: torch.Tensor, loss: float,
              state: State) -> tuple[torch.Tensor, State]:
        size = decayed_step(self.step_size, state["iteration"], self.config.steps, self.config.step_decay)
        return pgd_step(T, G, state["T0"], self.eps, size), {}
