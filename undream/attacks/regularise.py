"""The objective's regularisers: smoothness, printability and camouflage of a texture.

Functions first (kornia style), on ``H×W×3`` torch tensors of sRGB values in [0, 1], each returning
a scalar tensor that autograd differentiates; :class:`Regularisers` holds a run's weights and
palettes (:class:`undream.spec.physical.RegulariseConfig`) and calls them. The attack maximises
``victim_loss − Σ w_i R_i(T)`` (:func:`objective`), so each term pulls the texture towards lower
values.

Smoothing. ``|x|`` is not differentiable at 0, and a texture's flat regions and its texels on a
palette colour sit exactly there; every absolute value and Euclidean distance below is the smooth
``sqrt(x² + δ²) − δ`` with ``δ`` = :data:`SMOOTH` (1e-3 in sRGB 0–1 units): 0 at 0, within δ of
``|x|`` everywhere, gradient 0 at 0 and ±1 away from it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from undream.errors import AttackError

SMOOTH = 1e-3  # δ of the smooth |x| (sRGB 0–1 units)
TERMS = ("tv", "nps", "camouflage")  # the recorded names are reg_<term>


def _check(name: str, T: Any) -> torch.Tensor:
    if not isinstance(T, torch.Tensor) or T.ndim != 3 or T.shape[2] != 3 or not T.is_floating_point():
        what = f"shape {tuple(T.shape)}, dtype {T.dtype}" if isinstance(T, torch.Tensor) else type(T).__name__
        raise AttackError(f"{name}: must be an H×W×3 floating tensor (sRGB 0–1), got {what}")
    return T


def smooth_abs(x: torch.Tensor, delta: float = SMOOTH) -> torch.Tensor:
    """``sqrt(x² + δ²) − δ``: ``|x|`` made differentiable at 0 (0 there, within ``δ`` of ``|x|``)."""
    return torch.sqrt(x * x + delta * delta) - delta


def total_variation(T: torch.Tensor, delta: float = SMOOTH) -> torch.Tensor:
    """Total variation of ``T`` (H×W×3, sRGB 0–1) as Thys et al. (2019): the mean over texels and
    channels of ``|T[i, j+1] − T[i, j]|`` plus the mean of ``|T[i+1, j] − T[i, j]|``, each ``|·|``
    the smooth :func:`smooth_abs`. 0 for a constant texture; at most 2 (a checkerboard of black and
    white)."""
    T = _check("T", T)
    zero = T.new_zeros(())
    across = smooth_abs(T[:, 1:] - T[:, :-1], delta).mean() if T.shape[1] > 1 else zero
    down = smooth_abs(T[1:] - T[:-1], delta).mean() if T.shape[0] > 1 else zero
    return across + down


def palette_distance(T: torch.Tensor, palette: torch.Tensor, delta: float = SMOOTH) -> torch.Tensor:
    """Mean over texels of the Euclidean distance (sRGB 0–1, smoothed as :func:`smooth_abs`) from
    each texel of ``T`` (H×W×3) to the nearest colour of ``palette`` (N×3, sRGB 0–1).

    The minimum is the hard one of Thys et al.'s code (their ``NPSCalculator``; Sharif et al. 2016
    write the product over palette colours instead, which vanishes on the same colours): its
    gradient pulls each texel straight towards its nearest palette colour (found without autograd,
    :func:`nearest_colour`; the distance to it is differentiated). 0 when every texel is a palette
    colour."""
    T = _check("T", T)
    if not isinstance(palette, torch.Tensor) or palette.ndim != 2 or palette.shape[1] != 3 or len(palette) == 0:
        raise AttackError(f"palette: must be an N×3 tensor of sRGB colours, got "
                          f"{tuple(palette.shape) if isinstance(palette, torch.Tensor) else type(palette).__name__}")
    texels = T.reshape(-1, 3)
    colours = palette.to(T)
    nearest = colours[nearest_colour(texels.detach(), colours)]  # the min's gradient goes to the nearest colour
    squared = ((texels - nearest) ** 2).sum(dim=-1)
    return (torch.sqrt(squared + delta * delta) - delta).mean()


CHUNK = 1 << 16  # texels per block of the nearest-colour search: its N×CHUNK distances stay small


def nearest_colour(texels: torch.Tensor, palette: torch.Tensor) -> torch.Tensor:
    """The index (M,) of the nearest colour of ``palette`` (N×3) to each of ``texels`` (M×3), Euclidean,
    searched a block of :data:`CHUNK` texels at a time (a 1024×1024 texture against 130 colours would
    otherwise hold a gigabyte of distances)."""
    out = torch.empty(len(texels), dtype=torch.long, device=texels.device)
    for start in range(0, len(texels), CHUNK):
        block = texels[start:start + CHUNK]
        out[start:start + CHUNK] = torch.cdist(block, palette).argmin(dim=1)
    return out


def non_printability(T: torch.Tensor, palette: torch.Tensor) -> torch.Tensor:
    """Non-printability score (Sharif et al. 2016): :func:`palette_distance` to a printable palette."""
    return palette_distance(T, palette)


def camouflage(T: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Camouflage term: :func:`palette_distance` to the colours of the object's background."""
    return palette_distance(T, background)


def palette_tensor(colours: Sequence[Sequence[float]], dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """A config's palette (sRGB 0–255 triplets) as an N×3 tensor of sRGB 0–1."""
    return torch.tensor(np.asarray(colours, np.float64) / 255.0, dtype=dtype).reshape(-1, 3)


@dataclass(frozen=True)
class Regularisers:
    """A run's regularisers: ``weights`` (term → w > 0) and the palettes (N×3 sRGB 0–1) they need."""

    weights: dict[str, float]
    palette: torch.Tensor | None = None
    background: torch.Tensor | None = None

    @classmethod
    def of(cls, config: Any) -> "Regularisers | None":
        """From a :class:`undream.spec.physical.RegulariseConfig`; None when no term is weighted."""
        if config is None or not config.active:
            return None
        weights = {t: float(getattr(config, t)) for t in TERMS if getattr(config, t) > 0}
        return cls(weights, None if config.palette_rgb is None else palette_tensor(config.palette_rgb),
                   None if config.background_rgb is None else palette_tensor(config.background_rgb))

    def values(self, T: torch.Tensor) -> dict[str, torch.Tensor]:
        """Each weighted term's value R_i(T) (unweighted), by name."""
        out = {}
        for term in self.weights:
            if term == "tv":
                out[term] = total_variation(T)
            elif term == "nps":
                out[term] = non_printability(T, self.palette)  # type: ignore[arg-type]
            else:
                out[term] = camouflage(T, self.background)  # type: ignore[arg-type]
        return out

    def __call__(self, T: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        """``Σ w_i R_i(T)`` (a scalar tensor) and each R_i as a float."""
        values = self.values(T)
        total = sum((self.weights[t] * v for t, v in values.items()), T.new_zeros(()))
        return total, {t: float(v.detach()) for t, v in values.items()}


def penalty(regs: Regularisers | None, texture: np.ndarray) -> float:
    """``Σ w_i R_i(T)`` of ``texture`` (H×W×3 sRGB 0–1) as a float; 0 without regularisers."""
    if regs is None:
        return 0.0
    with torch.no_grad():
        return float(regs(torch.from_numpy(np.asarray(texture, np.float64)))[0])


def objective(regs: Regularisers | None, texture: np.ndarray, grad: torch.Tensor, loss: float,
              seen: torch.Tensor | None = None) -> tuple[torch.Tensor, float, dict[str, float]]:
    """The attack's objective ``victim_loss − Σ w_i R_i(T)`` and its gradient w.r.t. ``texture``.

    ``texture``: T (H×W×3 sRGB 0–1); ``grad`` and ``loss``: the victim's mean gradient and loss over
    the iteration's frames. The regularisers' gradient is computed in float64 and counts only on
    texels some frame has seen (``seen``, H×W bool: the attack's mask so far or'ed with the texels
    the victim's gradient reaches), so a texel no frame sees keeps its value as the attack's
    contract says (:mod:`undream.attacks.base`). Returns (G, loss, record): ``record`` holds
    ``loss_victim``, ``loss_total`` and ``reg_<term>`` of each weighted term (unweighted values).
    Without regularisers: (grad, loss, {}).
    """
    if regs is None:
        return grad, loss, {}
    T = torch.from_numpy(np.asarray(texture, np.float64)).requires_grad_(True)
    total, values = regs(T)
    (g_reg,) = torch.autograd.grad(total, T)
    mask = (grad != 0).any(dim=-1) if seen is None else (seen | (grad != 0).any(dim=-1))
    G = grad - torch.where(mask[..., None], g_reg, torch.zeros_like(g_reg)).to(grad.dtype)
    value = float(loss) - float(total.detach())
    record = {"loss_victim": float(loss), "loss_total": value, **{f"reg_{t}": v for t, v in values.items()}}
    return G, value, record
