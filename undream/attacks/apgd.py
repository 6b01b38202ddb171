"""Auto-PGD, L∞ (Croce & Hein, ICML 2020, Algorithm 1), as a farm step.

Follows the authors' reference code (fra31/auto-attack,
``autoattack/autopgd_base.py``, ``APGDAttack.attack_single_run``, L∞ branch):

- step size η starts at ``2ε`` (``attack.step_size``, when given, sets another η₀); the first step
  is plain projected sign ascent,
  ``x_1 = P(x_0 + η·sign ∇f(x_0))``; later ones add momentum α = 0.75:
  ``z = P(x_k + η·sign ∇f(x_k))``,
  ``x_{k+1} = P(x_k + α(z − x_k) + (1 − α)(x_k − x_{k−1}))``;
- checkpoints: the first period is ``max(int(0.22N), 1)`` iterations, each next
  one ``size_decr = max(int(0.03N), 1)`` shorter, never below
  ``max(int(0.06N), 1)`` (:func:`apgd_checkpoints`). For N = 100 they fall after
  iterations 22, 41, 57, 70, 80, 87, 93 and 99, as the paper's
  ``w_j = ⌈p_j N⌉`` with ``p_{j+1} = p_j + max(p_j − p_{j−1} − 0.03, 0.06)``;
- at a checkpoint η halves when (1) at most ρ·period of the steps since the
  last checkpoint increased the loss, or (2) η was not halved at the last
  checkpoint and the best loss has not grown since (:func:`apgd_should_halve`);
  on halving, the iterate restarts from the best point x_max, with its
  gradient (no new evaluation), and the next momentum term is
  ``x_max − x_{k−1}`` (as the reference's ``x_adv_old`` makes it);
- the random start is ``x_0 + ε·t/‖t‖∞`` with ``t`` uniform in [-1, 1].

Order of evaluation. The reference evaluates right after stepping::

    evaluate x_0
    for i in 0..N-1:  step x_i → x_{i+1};  evaluate x_{i+1};  bookkeeping(x_{i+1})

where bookkeeping is "update the best point; count increases; at a
checkpoint maybe halve η and replace x_{i+1} by x_max". The farm evaluates,
then steps: call ``c`` of :meth:`APGD.step` receives ``x_c`` with its loss and
gradient, so it does the reference's tail of iteration ``c − 1``
(``bookkeeping(x_c)``; for ``c = 0`` the initialisation) and then the head of
iteration ``c`` (the step to ``x_{c+1}``). Both produce the same iterates;
:meth:`APGD.final` does ``bookkeeping(x_N)``'s best-point part and returns x_max,
the reference's result.

Deliberate differences from the reference code:

- the first checkpoint counts the increase f(x_1) > f(x_0), as the paper says;
  the reference compares f(x_1) with ``loss_steps[-1]``, an unfilled slot that
  holds 0, so its decision depends on the sign of the loss. Here adding a
  constant to the loss never changes an iterate;
- one texture, not a batch: the loss is a scalar (the frames' mean);
- no early stop on success (the farm's metrics judge success), no restarts;
- ``attack.step_size`` as η₀, an option the reference lacks. With a smoothness term a first step of
  2ε makes the texture so rough that no later point scores above the start; on the stop-sign job a
  first step of PGD's size fared no better (docs/results.md, "Smooth and printable textures").

The loss is the one the victim computes (CE or DLR, :mod:`undream.victims.losses`).
With a minibatch of frames the loss comparisons mix frame subsets: use all
frames (``frames_per_step: null``) with APGD.
"""
from __future__ import annotations

import math
from typing import Any

import torch

from undream.attacks.base import Attack, State, loss_value, project_linf, register

MOMENTUM = 0.75


def apgd_schedule(n_iter: int) -> tuple[int, int, int]:
    """``(first period, minimum period, decrement)`` as the reference derives them."""
    return (max(int(0.22 * n_iter), 1), max(int(0.06 * n_iter), 1),
            max(int(0.03 * n_iter), 1))


def apgd_checkpoints(n_iter: int) -> list[int]:
    """Iteration counts ``w_j <= N`` after which the step size is checked."""
    period, least, decr = apgd_schedule(n_iter)
    marks, w = [], period
    while w <= n_iter:
        marks.append(w)
        period = max(period - decr, least)
        w += period
    return marks


def apgd_should_halve(n_increase: int, period: int, rho: float, halved_last: bool,
                      best_at_last_check: float, best: float) -> bool:
    """The checkpoint rule: condition 1 (oscillation) or condition 2 (stall)."""
    oscillating = n_increase <= period * rho
    stalled = (not halved_last) and best_at_last_check >= best
    return oscillating or stalled


def apgd_move(x: torch.Tensor, x_prev: torch.Tensor, grad: torch.Tensor, T0: torch.Tensor,
              eps: float, eta: float, a: float) -> torch.Tensor:
    """``P(x + a(z − x) + (1 − a)(x − x_prev))`` with ``z = P(x + η·sign(grad))``."""
    z = project_linf(x + eta * torch.sign(grad), T0, eps)
    return project_linf(x + (z - x) * a + (x - x_prev) * (1 - a), T0, eps)


@register
class APGD(Attack):
    """Auto-PGD (L∞); ``config.steps`` is N, ``config.rho`` is ρ; η starts at ``config.step_size``,
    2ε when it is None."""

    name = "apgd"
    needs_final_loss = True  # the best point seen counts the last texture's loss

    @property
    def first_step(self) -> float:
        """η₀ in 0–1 units: ``config.step_size`` when given, else ``2ε`` (the paper's)."""
        c = self.config
        return c.step_size / 255.0 if c.step_size is not None else 2.0 * self.eps

    def _random_delta(self, T0: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        t = 2 * torch.rand(T0.shape, generator=gen, dtype=T0.dtype, device=T0.device) - 1
        return self.eps * (t / (t.abs().max() + 1e-12))

    def _init_state(self, T: torch.Tensor) -> State:
        period, _, _ = apgd_schedule(self.config.steps)
        return {"eta": self.first_step, "period": period, "counter": 0, "n_increase": 0,
                "loss_prev": -math.inf, "loss_best": -math.inf,
                "loss_best_last_check": -math.inf, "halved_last_check": True,
                "halvings": [], "x_prev": T.clone(), "x_best": T.clone(),
                "grad_best": torch.zeros_like(T)}

    def _step(self, T: torch.Tensor, G: torch.Tensor, loss: float,
              state: State) -> tuple[torch.Tensor, State]:
        c = state["iteration"]
        if c == 0:
            s: dict[str, Any] = {"loss_prev": loss, "loss_best": loss,
                                 "loss_best_last_check": loss, "x_best": T.clone(),
                                 "grad_best": G.clone()}
            x, grad = T, G
        else:
            s, x, grad = self._bookkeeping(T, G, loss, state)
        eta = s.get("eta", state["eta"])
        a = 1.0 if c == 0 else MOMENTUM
        T_next = apgd_move(x, state["x_prev"], grad, state["T0"], self.eps, eta, a)
        s["x_prev"] = x.clone() if x is T else x
        return T_next, s

    def _bookkeeping(self, T: torch.Tensor, G: torch.Tensor, loss: float,
                     state: State) -> tuple[State, torch.Tensor, torch.Tensor]:
        """The reference's end of iteration ``c − 1`` for ``x_c = T``."""
        s: dict[str, Any] = {"n_increase": state["n_increase"] + int(loss > state["loss_prev"]),
                             "loss_prev": loss, "counter": state["counter"] + 1}
        if loss > state["loss_best"]:
            s.update(x_best=T.clone(), grad_best=G.clone(), loss_best=loss)
        best = s.get("loss_best", state["loss_best"])
        x, grad = T, G
        if s["counter"] == state["period"]:
            halve = apgd_should_halve(s["n_increase"], state["period"], self.config.rho,
                                      state["halved_last_check"],
                                      state["loss_best_last_check"], best)
            s.update(halved_last_check=halve, loss_best_last_check=best, counter=0,
                     n_increase=0)
            if halve:
                s["eta"] = state["eta"] / 2.0
                s["halvings"] = [*state["halvings"], state["iteration"]]
                x = s.get("x_best", state["x_best"])
                grad = s.get("grad_best", state["grad_best"])
            _, least, decr = apgd_schedule(self.config.steps)
            s["period"] = max(state["period"] - decr, least)
        return s, x, grad

    def final(self, T: torch.Tensor, loss: Any, state: State) -> torch.Tensor:
        """The best point seen, counting ``T`` (evaluated after the last step)."""
        self._check_state(state)
        if state["iteration"] == 0 or loss_value(loss) > state["loss_best"]:
            return T
        return state["x_best"]
