"""Defended victims (issue 45): each input transform's known answers and shapes, how the gradient
passes each (exact, BPDA, EOT), the seeded draws, boxes mapped through resize-and-pad, and bad
settings one line each. The run's path is tests/test_defended_runs.py."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from undream.errors import SpecError, VictimError
from undream.spec.defence import DefenceConfig, DefenceStep
from undream.spec.run import RunConfig
from undream.victims import Classifier, Detector, Target
from undream.victims.defended import DefendedVictim, attacker_view, defend
from undream.victims.defences import (
    backward_rule, bit_depth, draw_resize_pad, gaussian_kernel, gaussian_smooth, jpeg, jpeg_approx, jpeg_tables,
    mean_smooth, median_smooth, resize_pad,
)

LABELS = ["a", "b", "c"]


def _images(b: int = 2, h: int = 12, w: int = 10, seed: int = 0) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).uniform(0.05, 0.95, (b, 3, h, w)).astype(np.float32))


class _Linear(torch.nn.Module):
    """Fixed random logits linear in the pixels (and a square, so the gradient depends on the input)."""

    def __init__(self, h: int, w: int) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(1)
        self.w = torch.nn.Parameter(torch.randn(len(LABELS), 3 * h * w, generator=g))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.flatten(1)
        return flat @ self.w.T + (flat ** 2) @ self.w.T.abs() * 0.1


def _victim(h: int = 12, w: int = 10) -> Classifier:
    return Classifier(_Linear(h, w), LABELS, name="linear")


def _defended(*steps: dict, **options) -> DefendedVictim:
    return DefendedVictim(_victim(), DefenceConfig.from_json({"steps": list(steps), **options}), seed=3)


def _grad(victim, x: torch.Tensor) -> torch.Tensor:
    x = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(victim.losses(x, Target(label=1), "ce").sum(), x)
    return g


# -- each transform: known answers and shapes ------------------------------------------------------

def test_bit_depth_rounds_to_its_levels():
    x = _images()
    one = bit_depth(x, 1)
    assert one.shape == x.shape and set(one.unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(one, (x >= 0.5).float())
    three = bit_depth(x, 2)
    assert set(np.round(three.unique().numpy() * 3, 5).tolist()) <= {0.0, 1.0, 2.0, 3.0}
    eight = torch.round(x * 255) / 255
    assert torch.allclose(bit_depth(eight, 8), eight, atol=1e-7)  # 8-bit values are kept


def test_median_removes_an_outlier_and_keeps_a_flat_image():
    flat = torch.full((1, 3, 9, 9), 0.3)
    spiked = flat.clone()
    spiked[0, :, 4, 4] = 1.0
    assert torch.equal(median_smooth(spiked, 3), flat)
    ramp = torch.linspace(0, 1, 9).view(1, 1, 1, 9).expand(1, 3, 9, 9).contiguous()
    assert torch.allclose(median_smooth(ramp, 5), ramp)  # a monotone ramp is its own median
    assert median_smooth(_images(h=7, w=5), 5).shape == (2, 3, 7, 5)
    # the K×K mean, the median's smooth stand-in
    assert torch.allclose(mean_smooth(spiked, 3)[0, 0, 4, 4], torch.tensor(0.3 + 0.7 / 9))


def test_gaussian_smooth_is_its_kernel_on_a_delta_and_keeps_a_flat_image():
    w = gaussian_kernel(1.0)
    assert len(w) == 7 and w.sum().item() == pytest.approx(1.0) and w[3] == w.max()
    delta = torch.zeros(1, 3, 11, 11)
    delta[0, :, 5, 5] = 1.0
    out = gaussian_smooth(delta, 1.0)
    assert torch.allclose(out[0, 0, 2:9, 2:9], torch.outer(w, w), atol=1e-7)
    assert torch.allclose(gaussian_smooth(torch.full((2, 3, 5, 6), 0.7), 2.5), torch.full((2, 3, 5, 6), 0.7))


def test_jpeg_is_real_jpeg():
    from io import BytesIO

    from PIL import Image

    x = _images(b=2, h=16, w=16)
    out = jpeg(x, 75)
    assert out.shape == x.shape and out.dtype == x.dtype and not out.requires_grad
    assert torch.allclose(out * 255, torch.round(out * 255), atol=1e-4)  # decoded 8-bit values
    u8 = (x[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    buf = BytesIO()
    Image.fromarray(u8).save(buf, format="JPEG", quality=75)
    expected = np.asarray(Image.open(BytesIO(buf.getvalue())).convert("RGB")).astype(np.float32) / 255
    assert np.array_equal(out[0].permute(1, 2, 0).numpy(), expected)  # Pillow's codec, byte for byte
    smooth = torch.linspace(0.2, 0.8, 16).view(1, 1, 1, 16).expand(1, 3, 16, 16).contiguous()
    assert (jpeg(smooth, 95) - smooth).abs().max() < 4 / 255
    assert (jpeg(x, 5) - x).abs().mean() > (jpeg(x, 95) - x).abs().mean()  # lower quality, more change


def test_the_differentiable_jpeg_approximation_tracks_the_codec():
    from io import BytesIO

    from PIL import Image

    assert jpeg_tables(50)[0, 0].tolist() == [16, 11, 10, 16, 24, 40, 51, 61]  # the standard's table at 50
    assert torch.equal(jpeg_tables(100), torch.ones(3, 8, 8, dtype=torch.float64))
    x = gaussian_smooth(_images(b=1, h=21, w=30, seed=4), 2.0)  # not whole 8×8 blocks

    def codec(q: int) -> torch.Tensor:  # Pillow without chroma subsampling, which the approximation skips
        buf = BytesIO()
        Image.fromarray((x[0] * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()).save(
            buf, format="JPEG", quality=q, subsampling=0)
        decoded = np.array(Image.open(BytesIO(buf.getvalue())).convert("RGB"), dtype=np.float32) / 255
        return torch.from_numpy(decoded).permute(2, 0, 1)[None]

    for q in (20, 50, 75):
        approx, real = jpeg_approx(x, q), codec(q)
        assert approx.shape == x.shape and 0 <= approx.min() and approx.max() <= 1
        assert (approx - real).abs().mean() < 0.6 * (real - x).abs().mean(), q  # nearer the codec than the input is
    xg = x.double().requires_grad_(True)
    (g,) = torch.autograd.grad(jpeg_approx(xg, 50).sum(), xg)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_resize_pad_places_the_image_where_its_draw_says():
    step = DefenceStep("resize_pad", scale=(0.5, 0.8), pad=0.25, fill=0.5)
    x = torch.zeros(1, 3, 16, 20)
    x[:, :, 4:12, 6:14] = 1.0  # a white box (x0, y0, x1, y1) = (6, 4, 14, 12)
    d = draw_resize_pad(step, (0, 1, 2), 16, 20)
    assert d.canvas == (20, 25) and 8 <= d.height <= 13 and 0 <= d.top <= 20 - d.height
    out = resize_pad(x, [d])
    assert out.shape == (1, 3, 20, 25)
    assert float(out[0, 0, 0, 0]) == 0.5 or float(out[0, 0, -1, -1]) == 0.5  # the grey canvas shows
    sx, sy, tx, ty = d.affine(16, 20)
    bright = (out[0, 0] > 0.75).nonzero()
    y0, x0 = bright.min(0).values.tolist()
    y1, x1 = (bright.max(0).values + 1).tolist()
    assert abs(x0 - (6 * sx + tx)) <= 1 and abs(x1 - (14 * sx + tx)) <= 1
    assert abs(y0 - (4 * sy + ty)) <= 1 and abs(y1 - (12 * sy + ty)) <= 1
    same = DefenceStep("resize_pad", scale=(1.0, 1.0))
    assert torch.equal(resize_pad(x, [draw_resize_pad(same, (0, 0, 0), 16, 20)]), x)  # scale 1, no pad: itself


# -- how the gradient passes each one -------------------------------------------------------------

@pytest.mark.parametrize("step", [{"jpeg": 60}, {"median": 3}, {"bits": 3}])
def test_bpda_gives_the_identitys_gradient_where_the_forward_is_not_differentiable(step):
    kind = next(iter(step))
    assert backward_rule(DefenceStep.from_json(step), "auto") == "identity"
    victim = _defended(step)
    x = _images()
    with torch.no_grad():
        y = victim.transform(x)[0]
    assert not torch.allclose(y, x, atol=1e-3)  # the forward does transform
    inner_at_y = _grad(victim.inner, y)  # d L(z)/dz at z = f(x): the identity on the backward pass
    assert torch.allclose(_grad(victim, x), inner_at_y, atol=1e-6), kind
    loss = victim.losses(x, Target(label=1), "ce")
    assert torch.allclose(loss, victim.inner.losses(y, Target(label=1), "ce"))  # the forward's value


def test_the_gaussian_is_differentiated_exactly_unless_bpda_is_asked():
    x = _images()
    exact, bpda = _defended({"gaussian": 1.2}), _defended({"gaussian": 1.2}, backward="bpda")
    xg = x.clone().requires_grad_(True)
    (autograd,) = torch.autograd.grad(exact.inner.losses(gaussian_smooth(xg, 1.2), Target(label=1), "ce").sum(), xg)
    assert torch.allclose(_grad(exact, x), autograd, atol=1e-6)
    identity = _grad(bpda.inner, gaussian_smooth(x, 1.2))
    assert torch.allclose(_grad(bpda, x), identity, atol=1e-6)
    assert not torch.allclose(autograd, identity, atol=1e-3)  # the two rules do differ
    assert torch.autograd.gradcheck(lambda t: gaussian_smooth(t, 0.8), (_images(1, 5, 6).double().requires_grad_(),))


def test_exact_and_smooth_backward_passes():
    x = _images()
    zero = _grad(_defended({"bits": 3}, backward="exact"), x)
    assert torch.count_nonzero(zero) == 0  # rounding's own gradient: the obfuscated one
    bpda_median, exact_median = _defended({"median": 3}), _defended({"median": 3}, backward="exact")
    g_exact = _grad(exact_median, x)
    assert torch.count_nonzero(g_exact) > 0 and not torch.allclose(g_exact, _grad(bpda_median, x), atol=1e-4)
    smooth = _defended({"median": 3}, backward="smooth")
    with torch.no_grad():
        y = median_smooth(x, 3)
    z = x.clone().requires_grad_(True)  # the mean's vjp of the inner gradient at the median's output
    (expected,) = torch.autograd.grad(mean_smooth(z, 3), z, grad_outputs=_grad(smooth.inner, y))
    assert torch.allclose(_grad(smooth, x), expected, atol=1e-6)
    smooth_jpeg = _defended({"jpeg": 50}, backward="smooth")
    y = jpeg(x, 50)
    (expected,) = torch.autograd.grad(jpeg_approx(z, 50), z, grad_outputs=_grad(smooth_jpeg.inner, y))
    assert torch.allclose(_grad(smooth_jpeg, x), expected, atol=1e-5)
    assert not torch.allclose(expected, _grad(smooth_jpeg.inner, y), atol=1e-3)  # not the identity's
    assert backward_rule(DefenceStep("resize_pad"), "bpda") == "exact"  # it moves pixels: never the identity


def test_resize_pad_is_differentiated_exactly():
    victim = DefendedVictim(_victim(), DefenceConfig.from_json({"resize_pad": {"scale": [0.6, 0.9]}}), seed=3)
    keyed = victim.for_frames(3, 7, [0, 1])
    x = _images()
    (d0, d1) = [draw_resize_pad(victim.defence.steps[0], (3, 7, f, 0, 0), 12, 10) for f in (0, 1)]
    xg = x.clone().requires_grad_(True)
    (autograd,) = torch.autograd.grad(victim.inner.losses(resize_pad(xg, [d0, d1]), Target(label=1), "ce").sum(), xg)
    assert torch.allclose(_grad(keyed, x), autograd, atol=1e-6)


# -- the random draws ------------------------------------------------------------------------------

def test_random_draws_repeat_from_the_seed_and_differ_between_iterations_and_frames():
    victim = _defended({"resize_pad": {"scale": [0.5, 1.0], "pad": 0.2}})
    x = _images(b=2)
    first = victim.for_frames(3, 4, [10, 11]).transform(x)[0]
    assert torch.equal(first, victim.for_frames(3, 4, [10, 11]).transform(x)[0])  # a retry repeats it
    assert not torch.equal(first, victim.for_frames(3, 5, [10, 11]).transform(x)[0])  # the next iteration
    assert not torch.equal(first, victim.for_frames(4, 4, [10, 11]).transform(x)[0])  # another seed
    same = torch.stack([x[0], x[0]])
    both = victim.for_frames(3, 4, [10, 12]).transform(same)[0]
    assert not torch.equal(both[0], both[1])  # frames draw apart
    # without frame keys: drawn from the image's content, the same whatever its batch
    alone = victim.transform(x[1:])[0]
    assert torch.equal(victim.transform(x)[0][1:], alone) and torch.equal(victim.transform(x)[0][1:], alone)


def test_eot_draws_average_the_loss_over_draws():
    x = _images(b=2)
    one = _defended({"resize_pad": {"scale": [0.5, 1.0]}}).for_frames(3, 4, [0, 1])
    four = _defended({"resize_pad": {"scale": [0.5, 1.0]}}, draws=4).for_frames(3, 4, [0, 1])
    stacked, _ = four.transform(x, 4)
    assert stacked.shape == (8, 3, 12, 10)
    per_draw = four.inner.losses(stacked, Target(label=1), "ce").view(4, 2)
    assert torch.allclose(four.losses(x, Target(label=1), "ce"), per_draw.mean(0))
    assert torch.allclose(one.losses(x, Target(label=1), "ce"), per_draw[0])  # draw 0 is the single draw
    losses, preds = four.loss_and_predict(x, Target(label=1), "ce")
    assert torch.allclose(losses, per_draw.mean(0)) and len(preds) == 2


# -- boxes through resize-and-pad ------------------------------------------------------------------

class _BrightBox(torch.nn.Module):
    """One query whose box is the bright pixels' extent (normalised cxcywh) and whose logits say class 0."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        boxes = []
        for im in x:
            ys, xs = (im[0] > 0.75).nonzero(as_tuple=True)
            h, w = im.shape[1:]
            x0, x1, y0, y1 = xs.min() / w, (xs.max() + 1) / w, ys.min() / h, (ys.max() + 1) / h
            boxes.append(torch.stack([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0]))
        logits = torch.tensor([[4.0, -4.0, -4.0, -4.0]]).expand(x.shape[0], 1, 4)
        return logits, torch.stack(boxes)[:, None]


def test_a_detectors_boxes_come_back_in_the_frames_pixels():
    det = Detector(_BrightBox(), LABELS, name="bright")
    victim = DefendedVictim(det, DefenceConfig.from_json({"resize_pad": {"scale": [0.5, 0.7], "pad": 0.3}}))
    x = torch.zeros(2, 3, 20, 24)
    x[:, :, 5:15, 4:16] = 1.0
    plain = det.predict(x)[0].boxes[0]
    assert torch.allclose(plain, torch.tensor([4.0, 5.0, 16.0, 15.0]))
    for pred in victim.for_frames(0, 3, [0, 1]).predict(x):
        assert torch.allclose(pred.boxes[0], plain, atol=2.5)  # mapped back (a pixel of rounding each side, scaled)
    raw = victim.for_frames(0, 3, [0, 1]).transform(x)[0]
    assert raw.shape == (2, 3, 26, 31)


# -- the wrapper and the attacker's view -----------------------------------------------------------

def test_the_wrapper_reuses_the_inner_victim_and_attacker_view_follows_adaptive():
    inner = _victim()
    victim = defend(inner, DefenceConfig.from_json([{"bits": 4}]), seed=2)
    assert isinstance(victim, DefendedVictim) and victim.inner is inner
    assert victim.task == "classification" and victim.labels == LABELS and victim.loss_kinds == inner.loss_kinds
    assert defend(inner, None) is inner
    again = defend(victim, DefenceConfig.from_json([{"jpeg": 50}]))
    assert again.inner is inner and again.defence.label == "jpeg 50"  # never wrapped twice
    with pytest.raises(VictimError, match="defended already"):
        DefendedVictim(victim, victim.defence)
    assert attacker_view(inner) is inner and attacker_view(victim) is victim
    assert attacker_view(victim, 0, 1, [0]).keys == ((0, 1, 0),)
    blind = defend(inner, DefenceConfig.from_json({"bits": 4, "adaptive": False}))
    assert attacker_view(blind, 0, 1, [0]) is inner  # a non-adaptive attack ignores the defence
    x = _images()
    assert [p.label for p in victim.predict(x)] == [p.label for p in inner.predict(bit_depth(x, 4))]
    with pytest.raises(VictimError, match="loss kind 'vanish'"):
        victim.losses(x, Target(label=1), "vanish")


# -- settings ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("defence, message", [
    ({"jpeg": 0}, "defence.steps[0].jpeg: must be a JPEG quality, an integer in 1..100, got 0"),
    ({"jpeg": float("inf")}, "defence.steps[0].jpeg: must be a JPEG quality, an integer in 1..100, got inf"),
    ({"median": 4}, "defence.steps[0].median: must be an odd kernel size in pixels"),
    ({"median": float("nan")}, "defence.steps[0].median: must be an odd kernel size in pixels"),
    ({"gaussian": -1}, "defence.steps[0].gaussian: must be a standard deviation in pixels in (0, 10], got -1"),
    ({"bits": 9}, "defence.steps[0].bits: must be a bit depth per channel, an integer in 1..8, got 9"),
    ({"resize_pad": {"scale": [0.1, 1]}}, "defence.steps[0].resize_pad.scale: must be [low, high]"),
    ({"resize_pad": {"pad": 2}}, "defence.steps[0].resize_pad.pad: must be in [0, 1]"),
    ({"blur": 3}, "defence.blur: unknown; valid are the defences jpeg, median, gaussian, bits, resize_pad"),
    ([{"jpeg": 75, "median": 3}], "defence.steps[0]: must be one mapping of a defence to its setting"),
    ([], "defence.steps: must be a non-empty list"),
    ("jpeg", "defence: must be a list of defences"),
    ({"jpeg": 75, "backward": "exact"}, "defence.backward: cannot differentiate jpeg exactly"),
    ({"jpeg": 75, "backward": "fast"}, "defence.backward: must be one of"),
    ({"median": 3, "draws": 4}, "defence.draws: must be 1 without a random defence"),
    ({"bits": 3, "adaptive": "no"}, "defence.adaptive: must be true"),
])
def test_bad_defence_settings_are_one_line(defence, message):
    with pytest.raises(SpecError) as err:
        RunConfig.from_json({"scene": "s", "defence": defence})
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_run_config_keeps_its_defence_through_json():
    cfg = RunConfig.from_json({"scene": "s", "defence": {"jpeg": 75, "median": 3, "adaptive": False}})
    assert cfg.defence.label == "jpeg 75 + median 3" and not cfg.defence.adaptive
    doc = json.loads(json.dumps(cfg.to_json()))
    assert doc["defence"] == {"steps": [{"jpeg": 75}, {"median": 3}], "backward": "auto", "adaptive": False,
                              "draws": 1}
    assert RunConfig.from_json(doc) == cfg
    rp = RunConfig.from_json({"scene": "s", "defence": [{"resize_pad": {"scale": [0.8, 1]}}], "seed": 1})
    assert RunConfig.from_json(json.loads(json.dumps(rp.to_json()))) == rp
    assert RunConfig.from_json({"scene": "s"}).to_json()["defence"] is None
