"""Adversarial training of a classifier against attacked textures (PGD-AT on the object's texture, the
PBCAT idea), and its robust accuracy on held-out images.

A data set made with ``shading`` (:func:`undream.training.dataset.render_shading`) holds, per image,
the object's radiance under a black and a white texture, its texture coordinates per pixel and its
coverage. The object is diffuse, so the image under any texture ``t`` is, to first order,

    sRGB( black + (white − black) · lin(t)(uv) )

(:func:`composite`): the same light, fog, camera and background, and ``t`` looked up where the object
shows, as Mitsuba's bitmap looks it up (bilinear, wrap repeat). PGD on ``t`` through this composite is
an attack on the object's texture in that image's scene, at the cost of a bilinear lookup instead of a
path-traced render; its fidelity (the composite of the image's own texture against the image) is
measured and recorded (:func:`composite_fidelity`). Training (:func:`adversarial_fit`) fine-tunes a
trained classifier on batches of which a share is the rendered images and the rest their composites
with textures attacked by PGD (random start, ``steps`` sign steps of ``2.5 ε / steps``) at a budget
drawn per image from ``eps`` (0–255, the L∞ distance of the sRGB texture from the image's own).

The victim it makes is judged where it matters by undream's own attack (the Mitsuba renderer, the
adaptive attack on the trained model itself): docs/results.md, "Defended victims".
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from undream.errors import DatasetError, VictimError
from undream.spec.io import check_new_folder, restored_on_failure
from undream.training.dataset import Dataset, load_datasets
from undream.training.textures import make_texture

SHADING_KEYS = ("black", "white", "uv", "coverage")


@dataclass(frozen=True)
class AdversarialConfig:
    """How to train: budgets ``eps`` (0–255, one drawn per attacked image), PGD ``steps`` per batch,
    ``epochs`` over the data, AdamW at ``lr`` (cosine schedule), ``clean_share`` of each batch
    seen as rendered, the rest attacked; ``eval_steps``: PGD steps of the held-out robust accuracy."""

    eps: tuple[int, ...] = (16, 50, 255)
    steps: int = 5
    epochs: int = 16
    lr: float = 1e-3
    batch_size: int = 64
    clean_share: float = 0.4
    seed: int = 0
    eval_steps: int = 20
    threads: int | None = None

    def __post_init__(self) -> None:
        if not self.eps or any(isinstance(e, bool) or not isinstance(e, int) or not 1 <= e <= 255 for e in self.eps):
            raise VictimError(f"eps: budgets must be integers in 1..255, got {list(self.eps)!r}")
        for name in ("steps", "epochs", "batch_size", "eval_steps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise VictimError(f"{name}: must be an integer >= 1, got {v!r}")
        if not 0.0 <= self.clean_share < 1.0:
            raise VictimError(f"clean_share: must be in [0, 1), got {self.clean_share!r}")
        if not self.lr > 0:
            raise VictimError(f"lr: must be > 0, got {self.lr!r}")


@dataclass
class ShadedSet:
    """A data set with its shading, as tensors: ``images`` N×3×H×W uint8 (the renders), ``labels`` N,
    ``textures`` N×S×S×3 float32 sRGB (each image's own, from its recipe), ``black``/``white``
    N×H×W×3 float32 linear, ``uv`` N×H×W×2, ``coverage`` N×H×W, and the :class:`Dataset`."""

    images: torch.Tensor
    labels: torch.Tensor
    textures: torch.Tensor
    black: torch.Tensor
    white: torch.Tensor
    uv: torch.Tensor
    coverage: torch.Tensor
    dataset: Dataset

    def __len__(self) -> int:
        return len(self.labels)

    def batch(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """The shading of the images ``idx``, as :func:`composite` takes it."""
        return {"black": self.black[idx], "white": self.white[idx], "uv": self.uv[idx]}


def load_shaded(folders: str | Path | list[str | Path]) -> ShadedSet:
    """A data set (one folder, or the parts of one: :func:`load_datasets`) made with ``shading``."""
    parts = [folders] if isinstance(folders, (str, Path)) else list(folders)
    ds = load_datasets(parts)
    roots = _record_roots(parts, ds)
    arrays: dict[str, list[np.ndarray]] = {k: [] for k in SHADING_KEYS}
    textures = []
    size = ds.images.shape[1]
    for root, rec in zip(roots, ds.records):
        if "shading" not in rec:
            raise DatasetError(f"{root}: image {rec['index']} has no shading; make the data set with "
                               "'undream victims make-dataset --shading'")
        try:
            with np.load(root / rec["shading"]) as z:
                for k in SHADING_KEYS:
                    arrays[k].append(np.asarray(z[k], np.float32))
        except (OSError, KeyError, ValueError) as err:
            raise DatasetError(f"{root / rec['shading']}: cannot read the shading ({err})") from None
        textures.append(make_texture(rec["params"]["texture"], size))
    t = {k: torch.from_numpy(np.stack(v)) for k, v in arrays.items()}
    return ShadedSet(torch.from_numpy(ds.images).permute(0, 3, 1, 2).contiguous(), torch.from_numpy(ds.labels),
                     torch.from_numpy(np.stack(textures).astype(np.float32)), t["black"], t["white"], t["uv"],
                     t["coverage"], ds)


def _record_roots(parts: list[str | Path], ds: Dataset) -> list[Path]:
    """The folder of each record of ``ds`` (the parts' records follow each other in order)."""
    if len(parts) == 1:
        return [Path(parts[0])] * len(ds)
    counts = [p["n"] for p in ds.metadata["parts"]]
    return [Path(f) for f, n in zip(parts, counts) for _ in range(n)]


# --------------------------------------------------------------------------- the composite

def srgb_to_linear_t(x: torch.Tensor) -> torch.Tensor:
    """sRGB [0, 1] → linear (IEC 61966-2-1), differentiable."""
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb_t(x: torch.Tensor) -> torch.Tensor:
    """Linear → sRGB, clipped to [0, 1], differentiable (the gradient of the clip is 0 outside)."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def composite(textures: torch.Tensor, black: torch.Tensor, white: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Images (B×3×H×W sRGB) of objects wearing ``textures`` (B×S×S×3 sRGB): ``black + (white −
    black) · lin(t)(uv)``, the texture looked up as Mitsuba's bitmap does (texel centres at
    ``(uv·S − ½)``, bilinear, wrap repeat; row 0 at v = 0)."""
    b, s = textures.shape[0], textures.shape[1]
    lin = srgb_to_linear_t(textures).permute(0, 3, 1, 2)  # B×3×S×S
    padded = F.pad(lin, (1, 1, 1, 1), mode="circular")  # one texel of wrap on each side
    pos = torch.remainder(uv, 1.0) * s - 0.5 + 1.0  # in the padded texture's pixels
    grid = (2.0 * pos + 1.0) / (s + 2) - 1.0
    albedo = F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=False)
    radiance = black.permute(0, 3, 1, 2) + (white - black).permute(0, 3, 1, 2) * albedo
    return linear_to_srgb_t(radiance)


def composite_fidelity(data: ShadedSet, batch: int = 200) -> dict[str, float]:
    """How well the composite of each image's own texture reproduces the image: PSNR (dB, 8-bit
    sRGB, over the whole set) and the mean absolute difference on the object's pixels (0–255)."""
    se, obj_err, obj_n, n = 0.0, 0.0, 0.0, 0
    for k in range(0, len(data), batch):
        idx = torch.arange(k, min(k + batch, len(data)))
        with torch.no_grad():
            img = composite(data.textures[idx], **data.batch(idx))
        ref = data.images[idx].float() / 255.0
        diff = (torch.round(img * 255.0) / 255.0 - ref)
        se += float((diff ** 2).sum())
        n += diff.numel()
        on = (data.coverage[idx] > 0.5).unsqueeze(1).expand_as(diff)
        obj_err += float(diff.abs()[on].sum()) * 255.0
        obj_n += float(on.sum())
    mse = se / max(n, 1)
    return {"psnr_db": round(10 * math.log10(1.0 / mse), 2) if mse > 0 else float("inf"),
            "object_mean_abs_255": round(obj_err / max(obj_n, 1.0), 2)}


# --------------------------------------------------------------------------- the attack

def pgd_textures(logits_of: Callable[[torch.Tensor], torch.Tensor], data: ShadedSet, idx: torch.Tensor,
                 eps: torch.Tensor, steps: int, gen: torch.Generator) -> torch.Tensor:
    """Textures (B×S×S×3 sRGB) within ``eps`` (B, in 0–1) of the images' own that maximise the
    cross-entropy of their true class: PGD with a uniform random start and ``steps`` sign steps of
    ``2.5 ε / steps``, projected on the ε-ball and [0, 1] after each."""
    t0, y, shading = data.textures[idx], data.labels[idx], data.batch(idx)
    e = eps.view(-1, 1, 1, 1)
    delta = (torch.rand(t0.shape, generator=gen) * 2.0 - 1.0) * e
    t = (t0 + delta).clamp(0.0, 1.0)
    for _ in range(steps):
        t.requires_grad_(True)
        loss = F.cross_entropy(logits_of(composite(t, **shading)), y)
        (grad,) = torch.autograd.grad(loss, t)
        with torch.no_grad():
            t = t + 2.5 * e / steps * grad.sign()
            t = torch.min(torch.max(t, t0 - e), t0 + e).clamp(0.0, 1.0)
    return t.detach()


def robust_accuracy(logits_of: Callable[[torch.Tensor], torch.Tensor], data: ShadedSet,
                    eps_255: list[int], steps: int, seed: int = 0, batch: int = 200) -> dict[str, Any]:
    """Held-out accuracy on the renders (``clean``), on the composites of their own textures
    (``composite``) and, per budget, on composites with textures attacked by :func:`pgd_textures`
    (``robust``: ε → accuracy)."""
    gen = torch.Generator().manual_seed(seed)
    correct = {"clean": 0, "composite": 0, **{e: 0 for e in eps_255}}
    for k in range(0, len(data), batch):
        idx = torch.arange(k, min(k + batch, len(data)))
        y = data.labels[idx]
        with torch.no_grad():
            correct["clean"] += int((logits_of(data.images[idx].float() / 255.0).argmax(1) == y).sum())
            correct["composite"] += int((logits_of(composite(data.textures[idx], **data.batch(idx))).argmax(1)
                                         == y).sum())
        for e in eps_255:
            t = pgd_textures(logits_of, data, idx, torch.full((len(idx),), e / 255.0), steps, gen)
            with torch.no_grad():
                correct[e] += int((logits_of(composite(t, **data.batch(idx))).argmax(1) == y).sum())
    n = len(data)
    return {"n_images": n, "clean": round(correct["clean"] / n, 4), "composite": round(correct["composite"] / n, 4),
            "robust": {str(e): round(correct[e] / n, 4) for e in eps_255}, "pgd_steps": steps, "seed": seed}


# --------------------------------------------------------------------------- training

def adversarial_fit(model: torch.nn.Module, data: ShadedSet, cfg: AdversarialConfig,
                    logits_of: Callable[[torch.Tensor], torch.Tensor], log: Callable[[str], None]) -> float:
    """Fine-tune ``model`` in place (see the module docstring); ``logits_of`` gives its logits for sRGB
    frames (a victim's ``forward_raw``, whose module ``model`` is); returns the seconds spent."""
    from undream.training.train import _schedule, augment, optimiser_step

    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    n, bs = len(data), cfg.batch_size
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=cfg.lr, weight_decay=5e-4)
    steps = cfg.epochs * math.ceil(n / bs)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _schedule(steps, max(1, steps // 30)))
    budgets = torch.tensor(cfg.eps, dtype=torch.float32) / 255.0
    start = time.perf_counter()
    for epoch in range(cfg.epochs):
        order = torch.randperm(n, generator=gen)
        total, seen, fooled, attacked = 0.0, 0, 0, 0
        for k in range(0, n, bs):
            idx = order[k:k + bs]
            n_clean = int(round(cfg.clean_share * len(idx)))
            att = idx[n_clean:]
            eps = budgets[torch.randint(len(budgets), (len(att),), generator=gen)]
            model.eval()  # the attack sees the model as it is judged (batch norm's running statistics)
            t = pgd_textures(logits_of, data, att, eps, cfg.steps, gen)
            with torch.no_grad():
                adv = composite(t, **data.batch(att))
                fooled += int((logits_of(adv).argmax(1) != data.labels[att]).sum())
                attacked += len(att)
            model.train()
            x = torch.cat([data.images[idx[:n_clean]].float() / 255.0, adv])
            y = torch.cat([data.labels[idx[:n_clean]], data.labels[att]])
            x, _ = augment(x, torch.zeros(len(y), 4), gen)
            loss = F.cross_entropy(logits_of(x), y, label_smoothing=0.1)
            total += optimiser_step(model, opt, sched, loss, 5.0) * len(y)
            seen += len(y)
        log(f"epoch {epoch + 1}/{cfg.epochs}: loss {total / seen:.4f}, the attack fooled the model on "
            f"{fooled}/{attacked} images before each update ({time.perf_counter() - start:.0f} s)")
    model.eval()
    return time.perf_counter() - start


def train_adversarial(data: list[str | Path], test: str | Path, base: str, out: str | Path,
                      cfg: AdversarialConfig, command: str = "", log: Callable[[str], None] = print
                      ) -> dict[str, Any]:
    """Fine-tune the classifier ``base`` (a bundled name or a folder) on ``data`` (parts made with
    ``shading``) by :func:`adversarial_fit`, save it to ``out`` with ``training.json`` (the base's
    record plus ``adversarial``: the config, the composite's fidelity, and the held-out robust
    accuracy of the base and of the new model) and its model card. ``out`` must be new or empty."""
    from undream.training.train import _save_and_evaluate, TrainConfig
    from undream.victims.registry import load_victim

    parts = list(data)
    if Path(test).resolve() in {Path(p).resolve() for p in parts}:
        raise DatasetError(f"{test}: is both a training dataset and the held-out one")
    check_new_folder(out, inputs=tuple(parts) + (test,))
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    victim = load_victim(base, task="classification")
    module = getattr(victim, "module", None)
    if module is None or not hasattr(module, "save_pretrained"):
        raise VictimError(f"base: {base} is not a Hugging Face classifier undream can fine-tune and save")
    train_set, test_set = load_shaded(parts), load_shaded(test)
    log(f"adversarial training: {len(train_set)} images, held out {len(test_set)}; budgets {list(cfg.eps)}")
    fidelity = {"train": composite_fidelity(train_set), "test": composite_fidelity(test_set)}
    log(f"composite against the renders: {fidelity}")

    budgets = sorted(set(cfg.eps) | {16, 50, 255})
    before = robust_accuracy(victim.forward_raw, test_set, budgets, cfg.eval_steps, cfg.seed)
    log(f"base on the held-out set: {before}")
    module.requires_grad_(True)
    seconds = adversarial_fit(module, train_set, cfg, victim.forward_raw, log)
    module.requires_grad_(False)
    after = robust_accuracy(victim.forward_raw, test_set, budgets, cfg.eval_steps, cfg.seed)
    log(f"trained on the held-out set: {after}")
    adversarial = {"base": base, "config": asdict(cfg), "composite_fidelity": fidelity,
                   "held_out_base": before, "held_out": after, "train_seconds": round(seconds, 1)}
    out = Path(out)
    check_new_folder(out, inputs=tuple(parts) + (test,))
    tc = TrainConfig(task="classification", seed=cfg.seed, epochs=cfg.epochs, lr=cfg.lr,
                     batch_size=cfg.batch_size, threads=cfg.threads)
    with restored_on_failure(out):
        return _save_and_evaluate(module, out, tc, seconds, train_set.dataset, test_set.dataset, parts, test,
                                  command, extra={"adversarial": adversarial})

