"""An image classifier victim around any ``torch.nn.Module``.

The module takes preprocessed ``B×3×h×w`` input and returns ``B×C`` logits (a
tensor, a tuple whose first item is the logits, or an object with a
``.logits`` attribute, as Hugging Face models return).
"""
from __future__ import annotations

from typing import Any, Sequence

import torch

from undream.errors import VictimError
from undream.spec.run import TASK_LOSSES
from undream.victims import losses
from undream.victims.base import ClassPrediction, Target, Victim, require_target_label
from undream.victims.preprocess import PreprocessConfig

CLASSIFICATION_LOSSES = TASK_LOSSES["classification"]  # one list: what a run config accepts


def _logits_of(out: Any) -> Any:
    if isinstance(out, torch.Tensor):
        return out
    if hasattr(out, "logits"):
        return out.logits
    if isinstance(out, (tuple, list)) and out:
        return out[0]
    return out


class Classifier(Victim):
    """Classification victim. Losses (all maximised by the attack):

    - ``ce``: cross-entropy of the true label (untargeted),
    - ``targeted_ce``: minus cross-entropy of ``Target.target_label``,
    - ``dlr``: Croce & Hein's Difference of Logits Ratio (untargeted),
    - ``margin``: Carlini & Wagner's margin clipped at ``losses.MARGIN_KAPPA`` (untargeted).
    """

    task = "classification"
    loss_kinds = CLASSIFICATION_LOSSES

    def __init__(self, module: torch.nn.Module, labels: Sequence[str],
                 preprocess: PreprocessConfig | None = None, name: str = "torch",
                 device: str | torch.device = "cpu") -> None:
        super().__init__(name, labels, preprocess or PreprocessConfig(), device)
        self.module = module.to(self.device).eval().requires_grad_(False)

    def forward_raw(self, images: torch.Tensor) -> torch.Tensor:
        """``B×C`` logits for sRGB [0, 1] ``B×3×H×W`` images (differentiable)."""
        logits = _logits_of(self.module(self.preprocess(images)))
        b = images.shape[0]
        if not isinstance(logits, torch.Tensor) or logits.shape != (b, self.num_classes):
            got = tuple(logits.shape) if isinstance(logits, torch.Tensor) else type(logits).__name__
            raise VictimError(f"victim {self.name!r}: model output must be logits of shape "
                              f"({b}, {self.num_classes}) (batch, classes), got {got}")
        return logits

    def _predictions_from(self, raw: torch.Tensor, images: torch.Tensor) -> list[ClassPrediction]:
        """The arg-max class and the softmax probabilities, per image."""
        probs = raw.float().softmax(-1).cpu()
        return [ClassPrediction(int(p.argmax()), p) for p in probs]

    def _losses_from(self, raw: torch.Tensor, images: torch.Tensor, targets: list[Target],
                     kind: str) -> torch.Tensor:
        """``B`` losses of ``kind`` from the ``B×C`` logits ``raw``."""
        y = torch.tensor([t.label for t in targets], dtype=torch.long, device=raw.device)
        if kind == "ce":
            return losses.ce_untargeted(raw, y, reduction="none")
        if kind == "dlr":
            return losses.dlr(raw, y, reduction="none")
        if kind == "margin":
            return losses.margin(raw, y, reduction="none")
        t = require_target_label(targets, kind)
        return losses.ce_targeted(raw, t.to(raw.device), reduction="none")
