"""Which way a frame's texture gradient is computed: the captured transport, or Mitsuba's prb backward.

``gradient: auto`` (the default) uses the transport cache
(:mod:`undream.render.transport`) on every frame whose gradient scene is
linear in the texture (checked once per frame by
:func:`~undream.render.transport.check_linear`, which refuses with a reason)
and prb elsewhere; ``transport`` requires it (a frame that is not linear is a
:class:`RenderError` naming the reason); ``prb`` never uses it.

A captured transport is exact for one sample pattern (its ``seed_grad``).
Reusing it for ever would keep that pattern's noise in every iteration's
gradient, so each frame is captured again with a new seed every
``transport_refresh`` iterations (measured: one cached gradient is as close
to a 256-spp reference as one fresh-seed prb gradient, and averaging
gradients of 4 captures is as close as averaging 4 fresh seeds). The seed of
a capture depends on the run's seed, the frame and the refresh epoch only,
so a run is reproducible whichever process computes which frame, and a
capture can be shared: with a :class:`TransportShelf` (the farm gives each
worker one over the blob store) a process first looks for a frame's
transport, and its linearity verdict, where another process left them.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from undream.errors import RenderError
from undream.lru import LastArray
from undream.render.differentiable import srgb_decode_deriv, texture_gradient
from undream.render.scene_cache import SceneCache

if TYPE_CHECKING:
    from undream.render.transport import Transport

log = logging.getLogger(__name__)

MODES = ("auto", "transport", "prb")
MAX_TRANSPORT_BYTES = 4 << 30  # beyond this, further frames use prb (logged once)


class TransportShelf(Protocol):
    """Where processes share captured transports and linearity verdicts of one scene."""

    def get(self, key: str) -> "Transport | None": ...

    def put(self, key: str, transport: "Transport") -> None: ...

    def get_verdict(self, index: int) -> tuple[bool, str | None]:
        """(known, reason): reason None means the frame is linear."""
        ...

    def put_verdict(self, index: int, reason: str | None) -> None: ...


def capture_seed(run_seed: int, index: int, epoch: int) -> int:
    """``seed_grad`` of frame ``index``'s capture in refresh epoch ``epoch`` (never a render's own seed)."""
    return (run_seed * 1_000_003 + epoch * 7_919 + index * 2 + 1_234_567) % (2**31 - 2) + 1


@dataclass
class GradientPath:
    """Per-process: each frame's transport (captured lazily) or the reason it uses prb."""

    scenes: SceneCache
    mode: str = "auto"
    refresh: int = 5
    run_seed: int = 0
    shelf: TransportShelf | None = None
    _transports: dict[int, tuple[int, "Transport"]] = field(default_factory=dict)  # index → (epoch, T)
    _verdicts: dict[int, str | None] = field(default_factory=dict)  # index → None (linear) or why not
    _over_budget: set[int] = field(default_factory=set)  # frames left to prb by MAX_TRANSPORT_BYTES
    _deriv: LastArray[np.ndarray] = field(default_factory=LastArray)  # the last texture → its sRGB derivative

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise RenderError(f"gradient: must be one of {', '.join(MODES)}, got {self.mode!r}")

    @property
    def transport_bytes(self) -> int:
        return sum(t.nbytes for _, t in self._transports.values())

    def method(self, index: int) -> str:
        """'transport' or 'prb' for frame ``index`` (decided on first use)."""
        return "transport" if self._usable(index) else "prb"

    def texture_gradient(self, index: int, texture_srgb: np.ndarray, grad_linear_image: np.ndarray,
                         spp: int, iteration: int, seed: int, conditions: Any = None) -> np.ndarray:
        """d(loss)/d(sRGB texture) (H_t×W_t×3) of frame ``index`` from d(loss)/d(linear image) (H×W×3).

        ``conditions`` (EOT, :mod:`undream.render.jitter`): the frame's camera and light moved
        as for its simulator render; prb then (a captured transport holds the frame's own ones).
        """
        if conditions is not None:
            return texture_gradient(self.scenes, index, texture_srgb, grad_linear_image, spp, seed, seed + 1,
                                    conditions)
        if not self._usable(index):
            return texture_gradient(self.scenes, index, texture_srgb, grad_linear_image, spp, seed, seed + 1)
        from undream.render.transport import capture_transport, texture_gradient_cached

        epoch = iteration // self.refresh
        held = self._transports.get(index)
        if held is None or held[0] != epoch:
            self._transports.pop(index, None)
            if self.transport_bytes > MAX_TRANSPORT_BYTES:
                self._over_budget.add(index)
                log.warning("frame %d: texture gradient by prb, not the transport cache: it holds %d MiB already",
                            index, self.transport_bytes >> 20)
                return texture_gradient(self.scenes, index, texture_srgb, grad_linear_image, spp, seed, seed + 1)
            seed_grad = capture_seed(self.run_seed, index, epoch)
            key = f"{index}-{seed_grad}-{spp}"
            t = self.shelf.get(key) if self.shelf is not None else None
            if t is None:
                t = capture_transport(self.scenes, index, spp, seed_grad)
                if self.shelf is not None:
                    self.shelf.put(key, t)
            self._transports[index] = held = (epoch, t)
        deriv = self._deriv.get(np.asarray(texture_srgb, np.float32), srgb_decode_deriv)  # once per texture
        return texture_gradient_cached(held[1], texture_srgb, grad_linear_image, deriv)

    def _usable(self, index: int) -> bool:
        if self.mode == "prb" or index in self._over_budget:
            return False
        if index not in self._verdicts:
            from undream.render.transport import check_linear

            known, reason = self.shelf.get_verdict(index) if self.shelf is not None else (False, None)
            if not known:
                reason = check_linear(self.scenes, index)
                if self.shelf is not None:
                    self.shelf.put_verdict(index, reason)
            self._verdicts[index] = reason
            if reason is not None and self.mode != "transport":
                log.warning("frame %d: texture gradient by prb, not the transport cache: %s", index, reason)
        reason = self._verdicts[index]
        if reason is not None and self.mode == "transport":
            raise RenderError(f"gradient: transport: frame {index} cannot use the transport cache ({reason})")
        return reason is None
