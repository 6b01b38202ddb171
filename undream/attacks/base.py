"""The attack interface, its registry and the L∞ projection every attack shares.

Textures are ``H×W×C`` floating tensors (C = 3 for RGB), sRGB, values in
[0, 1]. Budgets in :class:`AttackConfig` are 0–255 units; ``Attack.eps`` is the
same budget in 0–1 units. The loss is the one the attack MAXIMISES, already
averaged over the iteration's frames, and ``G`` is its gradient w.r.t. ``T``::

    attack = make_attack(config)
    T, state = attack.start(T0, visible=mask)          # first texture to evaluate
    for k in range(config.steps):
        loss, G = <mean over frames of L and dL/dT, at T>
        T, state = attack.step(T, G, loss, state)
    result = attack.final(T, loss_at_T, state)          # APGD: the best point seen

``step`` is pure: it never mutates its arguments and its result depends only on
the config and ``(T, G, loss, state)``; the state is a flat dict of tensors and
JSON values (:mod:`undream.attacks.state` turns it into plain JSON and back).

Visibility. ``start`` takes ``visible``, an ``H×W`` bool mask of the texels some
frame can see (from a gradient pass at ``T0`` or the scene's UV coverage);
None means every texel. The random start perturbs visible texels only. Each
step grows the mask by the texels whose gradient is non-zero in some channel
("seen so far") and leaves every texel outside it at its current value, bit
for bit. So a texel no frame ever sees keeps its starting value ``T0``; with
``visible=None`` and a random start it keeps its random start value.

Smoothed gradients. With ``config.grad_blur`` σ > 0, ``step`` smooths ``G`` by a
Gaussian of σ texels (:func:`blur_gradient`) after the "seen so far" mask is
taken from the raw gradient and before the attack's own step reads it.

Non-finite gradients. The reduce step drops frames whose gradient is not
finite, but ``step`` defends anyway: NaN and ±Inf entries of ``G`` count as 0
(no information about that texel) and their number is added to
``state["nonfinite"]``. A non-finite loss counts as -inf (never the best, never
an increase). ``T`` and ``T0`` must be finite and in [0, 1]: anything else is an
:class:`AttackError`, so the texture can never become NaN.
"""
from __future__ import annotations

import importlib
import math
import numbers
from typing import Any, Callable, ClassVar, TypeVar

import torch

from undream.errors import AttackError
from undream.spec.attack import AttackConfig
from undream.attacks.state import state_from_dict, state_to_dict
from undream.errors import SpecError

__all__ = ["Attack", "AttackConfig", "AttackError", "attack_names", "blur_gradient", "finite_gradient",
           "make_attack", "project_linf", "register"]

State = dict[str, Any]
_REGISTRY: dict[str, type["Attack"]] = {}
_BUILTIN = ("undream.attacks.pgd", "undream.attacks.apgd", "undream.attacks.mifgsm",
            "undream.attacks.adam")
A = TypeVar("A", bound=type["Attack"])


# --------------------------------------------------------------------------- functions

def project_linf(T: torch.Tensor, T0: torch.Tensor, eps: float) -> torch.Tensor:
    """Closest point to ``T`` in the ε ball around ``T0`` (L∞, 0–1 units) ∩ [0, 1].

    Both sets are boxes per texel, so clamping to one then the other is the exact
    projection onto their intersection (non-empty because ``T0`` is in [0, 1]).
    Written as Croce & Hein's reference code writes it.
    """
    return torch.clamp(torch.min(torch.max(T, T0 - eps), T0 + eps), 0.0, 1.0)


def decayed_step(step_size: float, iteration: int, steps: int, decay: str) -> float:
    """The sign-step size of ``iteration`` (0-based) of ``steps`` under ``attack.step_decay``."""
    if decay == "none":
        return step_size
    if decay == "cosine":
        return step_size * 0.5 * (1.0 + math.cos(math.pi * min(iteration, steps) / steps))
    raise AttackError(f"attack.step_decay: must be none or cosine, got {decay!r}")


def blur_gradient(G: torch.Tensor, sigma: float) -> torch.Tensor:
    """``G`` (``H×W×C``) smoothed by a Gaussian of σ ``sigma`` texels, each channel alone.

    Separable, truncated at 3σ (at most the texture's longer side) and normalised to sum 1, so a
    constant gradient stays itself; the edges repeat their last texel. ``sigma`` 0 returns ``G``.
    """
    if sigma <= 0:
        return G
    height, width, _ = G.shape
    radius = max(1, min(math.ceil(3 * sigma), max(height, width)))
    offsets = torch.arange(-radius, radius + 1, dtype=G.dtype, device=G.device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    planes = G.permute(2, 0, 1)[:, None]  # C×1×H×W
    planes = torch.nn.functional.pad(planes, (radius, radius, radius, radius), mode="replicate")
    planes = torch.nn.functional.conv2d(planes, kernel.view(1, 1, 1, -1))
    planes = torch.nn.functional.conv2d(planes, kernel.view(1, 1, -1, 1))
    return planes[:, 0].permute(1, 2, 0).contiguous()


def finite_gradient(G: torch.Tensor) -> tuple[torch.Tensor, int]:
    """``G`` with NaN and ±Inf entries set to 0, and how many there were."""
    ok = torch.isfinite(G)
    bad = int(ok.numel() - int(ok.sum()))
    return (G if bad == 0 else torch.where(ok, G, torch.zeros_like(G))), bad


def loss_value(loss: Any) -> float:
    """The loss as a Python float; non-finite values become -inf."""
    if isinstance(loss, torch.Tensor):
        if loss.numel() != 1:
            raise AttackError(f"loss: must be one number (the mean over frames), "
                              f"got a tensor of shape {tuple(loss.shape)}")
        loss = loss.item()
    if isinstance(loss, bool) or not isinstance(loss, numbers.Real):
        raise AttackError(f"loss: must be a number, got {loss!r}")
    value = float(loss)
    return value if math.isfinite(value) else -math.inf


def check_texture(name: str, T: Any, like: torch.Tensor | None = None) -> torch.Tensor:
    """``T`` if it is a finite ``H×W×C`` floating tensor in [0, 1] (shaped ``like``)."""
    if not isinstance(T, torch.Tensor) or T.ndim != 3 or not T.is_floating_point():
        what = f"shape {tuple(T.shape)}, dtype {T.dtype}" if isinstance(T, torch.Tensor) \
            else type(T).__name__
        raise AttackError(f"{name}: must be an H×W×C floating tensor, got {what}")
    if like is not None and T.shape != like.shape:
        raise AttackError(f"{name}: shape {tuple(T.shape)} differs from the starting "
                          f"texture's {tuple(like.shape)}")
    if not bool(torch.isfinite(T).all()) or bool((T < 0).any()) or bool((T > 1).any()):
        raise AttackError(f"{name}: values must be finite and in [0, 1] (sRGB), got range "
                          f"[{T.min().item()}, {T.max().item()}]")
    return T


def _check_visible(visible: Any, T0: torch.Tensor) -> torch.Tensor:
    if visible is None:
        return torch.ones(T0.shape[:2], dtype=torch.bool, device=T0.device)
    mask = torch.as_tensor(visible, device=T0.device)
    if mask.shape != T0.shape[:2] or mask.dtype != torch.bool:
        raise AttackError(f"visible: must be an H×W bool mask of shape {tuple(T0.shape[:2])}, "
                          f"got shape {tuple(mask.shape)}, dtype {mask.dtype}")
    return mask.clone()


# --------------------------------------------------------------------------- the interface

class Attack:
    """One registered attack: holds the config and calls the step functions.

    Subclasses set ``name``, and implement ``_step`` (and ``_init_state`` when
    they carry state of their own); ``start``, ``step``, masking, the checks and
    the final projection live here.
    """

    name: ClassVar[str] = ""
    needs_final_loss: ClassVar[bool] = False  # does :meth:`final` read the last texture's loss?

    def __init__(self, config: AttackConfig) -> None:
        self.config = config

    @property
    def eps(self) -> float:
        """The L∞ budget in 0–1 units of the texture."""
        return self.config.eps / 255.0

    def project(self, T: torch.Tensor, T0: torch.Tensor) -> torch.Tensor:
        """Projection onto the ε ball around ``T0`` and onto [0, 1]."""
        return project_linf(T, T0, self.eps)

    def start(self, T0: torch.Tensor, visible: torch.Tensor | None = None,
              generator: torch.Generator | None = None) -> tuple[torch.Tensor, State]:
        """The first texture to evaluate (``T0`` or a random start) and the state.

        ``generator`` defaults to one seeded with ``config.seed``.
        """
        T0 = check_texture("T0", T0)
        mask = _check_visible(visible, T0)
        T = T0.clone()
        if self.config.random_start:
            gen = generator if generator is not None else \
                torch.Generator(device=T0.device).manual_seed(self.config.seed)
            moved = self.project(T0 + self._random_delta(T0, gen), T0)
            T = torch.where(mask[..., None], moved, T0)
        state: State = {"attack": self.name, "iteration": 0, "T0": T0.clone(),
                        "visible": mask, "nonfinite": 0}
        state.update(self._init_state(T))
        return T, state

    def step(self, T: torch.Tensor, G: torch.Tensor, loss: Any,
             state: State) -> tuple[torch.Tensor, State]:
        """One iteration: ``T`` evaluated (``loss``, gradient ``G``) → ``T_next``."""
        self._check_state(state)
        T0 = state["T0"]
        T = check_texture("T", T, like=T0)
        if not isinstance(G, torch.Tensor) or G.shape != T.shape:
            what = tuple(G.shape) if isinstance(G, torch.Tensor) else type(G).__name__
            raise AttackError(f"G: must be a tensor shaped like T {tuple(T.shape)}, got {what}")
        G, bad = finite_gradient(G.to(T))
        seen = state["visible"] | (G != 0).any(dim=-1)
        G = blur_gradient(G, self.config.grad_blur)  # after `seen`: blurring shows no texel to a frame
        raw, own = self._step(T, G, loss_value(loss), state)
        T_next = torch.where(seen[..., None], self.project(raw, T0), T)
        return T_next, {**state, **own, "iteration": state["iteration"] + 1,
                        "visible": seen, "nonfinite": state["nonfinite"] + bad}

    def final(self, T: torch.Tensor, loss: Any, state: State) -> torch.Tensor:
        """The texture to report after the last step, given ``T``'s loss: ``T``."""
        return T

    @staticmethod
    def state_to_dict(state: State) -> dict[str, Any]:
        """Plain JSON-able form of ``state``."""
        return state_to_dict(state)

    @staticmethod
    def state_from_dict(data: dict[str, Any]) -> State:
        """Inverse of :meth:`state_to_dict`."""
        return state_from_dict(data)

    # -- for subclasses

    def _random_delta(self, T0: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """Uniform in [-ε, ε] per channel (Madry et al.)."""
        u = torch.rand(T0.shape, generator=gen, dtype=T0.dtype, device=T0.device)
        return (2 * u - 1) * self.eps

    def _init_state(self, T: torch.Tensor) -> State:
        return {}

    def _step(self, T: torch.Tensor, G: torch.Tensor, loss: float,
              state: State) -> tuple[torch.Tensor, State]:
        raise NotImplementedError

    def _check_state(self, state: Any) -> None:
        if not isinstance(state, dict) or state.get("attack") != self.name:
            made = state.get("attack") if isinstance(state, dict) else type(state).__name__
            raise AttackError(f"state: made by attack {made!r}, not {self.name!r}; "
                              "start() makes a fresh one")
        missing = [k for k in ("iteration", "T0", "visible", "nonfinite") if k not in state]
        if missing:
            raise AttackError(f"state: missing {', '.join(missing)}")


# --------------------------------------------------------------------------- registry

def register(cls: A) -> A:
    """Class decorator: make ``cls`` available under ``cls.name``."""
    if not cls.name:
        raise AttackError(f"register: {cls.__qualname__} has no name")
    other = _REGISTRY.get(cls.name)
    if other is not None and other is not cls:
        raise AttackError(f"register: name {cls.name!r} is taken by {other.__qualname__}")
    _REGISTRY[cls.name] = cls
    return cls


def unregister(name: str) -> None:
    """Forget an attack (for tests and plugins)."""
    _REGISTRY.pop(name, None)


def _load_builtins() -> None:
    for module in _BUILTIN:
        importlib.import_module(module)


def attack_names() -> list[str]:
    """Registered attack names, sorted."""
    _load_builtins()
    return sorted(_REGISTRY)


def make_attack(config: AttackConfig) -> Attack:
    """The attack ``config.name`` names; unknown names are a :class:`SpecError`."""
    _load_builtins()
    cls: Callable[[AttackConfig], Attack] | None = _REGISTRY.get(config.name)
    if cls is None:
        raise SpecError(f"attack.name: unknown attack {config.name!r}; "
                        f"valid names are {', '.join(sorted(_REGISTRY))}")
    return cls(config)
