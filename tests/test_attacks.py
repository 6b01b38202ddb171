"""Attacks: registry, APGD against a transcription of the reference code, known
answers, projection, visibility, non-finite gradients, state round trip.

The reference for Auto-PGD is fra31/auto-attack ``autoattack/autopgd_base.py``
(``APGDAttack.attack_single_run``, L∞ branch); :func:`reference_apgd` below is
that loop, transcribed for one sample, with the one deliberate difference
marked where it is.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from undream.attacks import (
    AttackConfig,
    AttackError,
    apgd_checkpoints,
    attack_names,
    average_frames,
    frame_batch,
    make_attack,
    project_linf,
    register,
    state_from_dict,
    state_to_dict,
)
from undream.attacks.apgd import apgd_should_halve
from undream.attacks.base import Attack, unregister
from undream.errors import SpecError

SHAPE = (4, 4, 3)
BUILTIN = ["adam", "apgd", "mifgsm", "pgd"]
CHECKPOINTS_100 = [22, 41, 57, 70, 80, 87, 93, 99]  # the reference's counter3 == k, N = 100


def attack(name: str, **kw) -> Attack:
    return make_attack(AttackConfig(name=name, **kw))


def run(att: Attack, f, T0: torch.Tensor, steps: int, visible=None, generator=None):
    """The farm's order: evaluate T, then step. Returns iterates T_1..T_N, state."""
    T, state = att.start(T0, visible=visible, generator=generator)
    iterates = [T]
    for _ in range(steps):
        loss, G = f(T)
        T, state = att.step(T, G, loss, state)
        iterates.append(T)
    return iterates, state


def smooth_nonconvex(seed: int = 1):
    """Deterministic f(T) = Σ a·sin(wT + c) + ½Σ sin(7·T·roll(T)), with its gradient."""
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(SHAPE, generator=g) + 0.5
    w = 20 + 40 * torch.rand(SHAPE, generator=g)
    c = 2 * math.pi * torch.rand(SHAPE, generator=g)

    def f(T: torch.Tensor):
        T = T.detach().clone().requires_grad_()
        loss = (a * torch.sin(w * T + c)).sum() + 0.5 * torch.sin(7 * T * T.roll(1, dims=1)).sum()
        (G,) = torch.autograd.grad(loss, T)
        return loss.detach(), G
    return f


def scripted(losses: list[float], seed: int = 3):
    """An oracle returning the n-th scripted loss and a seeded random gradient on call n."""
    g = torch.Generator().manual_seed(seed)
    calls = iter(range(10 ** 6))

    def f(T: torch.Tensor):
        n = next(calls)
        return torch.tensor(losses[n]), torch.randn(T.shape, generator=g)
    return f


# --------------------------------------------------------------------------- the reference

def reference_apgd(f, x: torch.Tensor, eps: float, n_iter: int, rho: float = 0.75,
                   rand_gen: torch.Generator | None = None, literal: bool = False):
    """``APGDAttack.attack_single_run``, norm 'Linf', one sample (batch of 1).

    ``literal=True`` keeps the reference's first comparison against 0 (see below).

    Left out: accuracy/``x_best_adv`` bookkeeping (it changes no iterate) and
    the L2/L1 branches. ``f`` maps an ``H×W×C`` texture to (loss, gradient).
    Returns the iterates x_adv after each step and x_best.
    """
    def f_batch(xb):
        loss, grad = f(xb[0])
        return loss.reshape(1).float(), grad[None]

    def normalize(t):
        m = t.abs().view(t.shape[0], -1).max(1)[0]
        return t / (m.view(-1, 1, 1, 1) + 1e-12)

    def check_oscillation(xs, j, k, k3):
        t = torch.zeros(xs.shape[1])
        for counter5 in range(k):
            t += (xs[j - counter5] > xs[j - counter5 - 1]).float()
        return (t <= k * k3 * torch.ones_like(t)).float()

    n_iter_2 = max(int(0.22 * n_iter), 1)
    n_iter_min = max(int(0.06 * n_iter), 1)
    size_decr = max(int(0.03 * n_iter), 1)

    x = x[None]
    if rand_gen is not None:
        t = 2 * torch.rand(x.shape, generator=rand_gen) - 1
        x_adv = x + eps * torch.ones_like(x).detach() * normalize(t)
    else:
        x_adv = x.clone()
    x_adv = x_adv.clamp(0., 1.)
    x_best = x_adv.clone()
    loss_steps = torch.zeros([n_iter, 1])

    loss_indiv, grad = f_batch(x_adv)
    grad_best = grad.clone()
    loss_best = loss_indiv.detach().clone()
    # DELIBERATE DIFFERENCE (see undream/attacks/apgd.py): the reference leaves
    # loss_steps[-1] at 0, and the first checkpoint compares f(x_1) with it;
    # the paper (and undream) compare f(x_1) with f(x_0).
    if not literal:
        loss_steps[-1] = loss_best

    step_size = 2. * eps * torch.ones([x.shape[0], 1, 1, 1])
    x_adv_old = x_adv.clone()
    k = n_iter_2 + 0
    counter3 = 0
    loss_best_last_check = loss_best.clone()
    reduced_last_check = torch.ones_like(loss_best)

    iterates = []
    for i in range(n_iter):
        with torch.no_grad():
            x_adv = x_adv.detach()
            grad2 = x_adv - x_adv_old
            x_adv_old = x_adv.clone()
            a = 0.75 if i > 0 else 1.0
            x_adv_1 = x_adv + step_size * torch.sign(grad)
            x_adv_1 = torch.clamp(torch.min(torch.max(x_adv_1, x - eps), x + eps), 0.0, 1.0)
            x_adv_1 = torch.clamp(torch.min(torch.max(
                x_adv + (x_adv_1 - x_adv) * a + grad2 * (1 - a), x - eps), x + eps), 0.0, 1.0)
            x_adv = x_adv_1 + 0.
        iterates.append(x_adv[0].clone())

        loss_indiv, grad = f_batch(x_adv)

        with torch.no_grad():
            y1 = loss_indiv.detach().clone()
            loss_steps[i] = y1 + 0
            ind = y1 > loss_best  # the reference's .nonzero().squeeze(), as a mask
            x_best[ind] = x_adv[ind].clone()
            grad_best[ind] = grad[ind].clone()
            loss_best[ind] = y1[ind] + 0
            counter3 += 1
            if counter3 == k:
                fl_oscillation = check_oscillation(loss_steps, i, k, rho)
                fl_reduce_no_impr = (1. - reduced_last_check) * (
                    loss_best_last_check >= loss_best).float()
                fl_oscillation = torch.max(fl_oscillation, fl_reduce_no_impr)
                reduced_last_check = fl_oscillation.clone()
                loss_best_last_check = loss_best.clone()
                if fl_oscillation.sum() > 0:
                    ind_fl_osc = fl_oscillation > 0
                    step_size[ind_fl_osc] /= 2.0
                    x_adv[ind_fl_osc] = x_best[ind_fl_osc].clone()
                    grad[ind_fl_osc] = grad_best[ind_fl_osc].clone()
                k = max(k - size_decr, n_iter_min)
                counter3 = 0
    return iterates, x_best[0]


# --------------------------------------------------------------------------- registry, config

def test_registry_lists_builtins_and_switches_by_name():
    assert set(BUILTIN) <= set(attack_names())
    config = AttackConfig(name="pgd", eps=8, steps=10)
    for name in BUILTIN:
        att = make_attack(dataclasses.replace(config, name=name))
        assert att.name == name and att.config.eps == 8.0


def test_unknown_attack_name_lists_the_valid_ones():
    with pytest.raises(SpecError, match=r"attack\.name: unknown attack 'pgd2'") as err:
        attack("pgd2")
    for name in BUILTIN:
        assert name in str(err.value)


def test_register_adds_an_attack_in_one_class():
    @register
    class Stay(Attack):
        name = "test_stay"

        def _step(self, T, G, loss, state):
            return T, {}

    try:
        att = attack("test_stay")
        T0 = torch.full(SHAPE, 0.25)
        T, state = att.start(T0)
        T, state = att.step(T, torch.ones(SHAPE), 1.0, state)
        assert torch.equal(T, T0) and state["iteration"] == 1
        with pytest.raises(AttackError, match="taken"):
            register(type("Other", (Attack,), {"name": "test_stay"}))
    finally:
        unregister("test_stay")
    assert "test_stay" not in attack_names()


@pytest.mark.parametrize("field, value", [
    ("eps", 0), ("eps", -1.0), ("eps", float("inf")), ("eps", "8"), ("steps", 0),
    ("steps", 2.5), ("step_size", 0.0), ("random_start", 1), ("momentum", -0.1),
    ("lr", 0), ("rho", 1.5), ("seed", -1), ("frames_per_step", 0), ("name", ""),
])
def test_config_rejects_bad_fields_naming_them(field, value):
    with pytest.raises(SpecError, match=rf"^attack\.{field}: (.*got )?{re.escape(repr(value))}"):
        AttackConfig(**{field: value})


def test_config_dict_round_trip_and_unknown_fields():
    config = AttackConfig(name="apgd", eps=16, steps=37, random_start=True, seed=5)
    data = json.loads(json.dumps(config.to_dict()))
    assert AttackConfig.from_dict(data) == config
    assert isinstance(config.eps, float)
    with pytest.raises(SpecError, match="unknown field.*epsilon.*valid fields are name, eps"):
        AttackConfig.from_dict({"name": "pgd", "epsilon": 8})


def test_config_module_imports_no_torch():
    code = ("import sys, undream.spec.attack, undream.attacks; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


# --------------------------------------------------------------------------- Auto-PGD

def paper_checkpoints(n_iter: int) -> list[int]:
    """Croce & Hein's w_j = ceil(p_j N), p_0 = 0, p_1 = 0.22, exactly (fractions)."""
    p = [Fraction(0), Fraction(22, 100)]
    while p[-1] + max(p[-1] - p[-2] - Fraction(3, 100), Fraction(6, 100)) <= 1:
        p.append(p[-1] + max(p[-1] - p[-2] - Fraction(3, 100), Fraction(6, 100)))
    return [math.ceil(pj * n_iter) for pj in p[1:]]


def test_apgd_checkpoints_for_100_match_paper_and_reference():
    assert paper_checkpoints(100) == CHECKPOINTS_100
    assert apgd_checkpoints(100) == CHECKPOINTS_100


def test_apgd_halves_at_exactly_the_checkpoints():
    """A constant loss never increases: condition 1 halves η at every checkpoint."""
    att = attack("apgd", eps=8, steps=100)
    _, state = run(att, lambda T: (torch.tensor(1.0), torch.ones(SHAPE)), torch.full(SHAPE, 0.5),
                   100)
    assert state["halvings"] == CHECKPOINTS_100
    assert state["eta"] == 2 * att.eps / 2 ** len(CHECKPOINTS_100)


def test_apgd_starts_at_the_step_size_when_one_is_given():
    """``attack.step_size`` is APGD's η₀: the first step moves each texel by it, and the halvings
    divide it; without one, η₀ is 2ε (above)."""
    att = attack("apgd", eps=255, steps=100, step_size=6)
    G = torch.tensor([1.0, -1.0, 0.0]).expand(SHAPE)
    T0 = torch.full(SHAPE, 0.5)
    iterates, state = run(att, lambda T: (torch.tensor(1.0), G), T0, 100)
    assert torch.allclose(iterates[1] - T0, torch.sign(G) * 6 / 255, atol=1e-7)
    assert state["halvings"] == CHECKPOINTS_100
    assert state["eta"] == pytest.approx(6 / 255 / 2 ** len(CHECKPOINTS_100))


@pytest.mark.parametrize("n_inc, period, halved_last, best_last, best, expected", [
    (16, 22, True, 0.0, 1.0, True),    # 16 <= 16.5: oscillating
    (17, 22, True, 0.0, 1.0, False),   # enough increases, halved last time
    (12, 16, True, 0.0, 1.0, True),    # 12 <= 12: the reference's <= at equality
    (17, 22, False, 1.0, 1.0, True),   # not halved last time and best unchanged: stalled
    (17, 22, False, 1.0, 1.5, False),  # not halved last time but best improved
    (17, 22, True, 1.0, 1.0, False),   # condition 2 needs "not halved last time"
])
def test_apgd_checkpoint_rule(n_inc, period, halved_last, best_last, best, expected):
    assert apgd_should_halve(n_inc, period, 0.75, halved_last, best_last, best) is expected


@pytest.mark.parametrize("eps, n_iter, random_start", [(8, 100, False), (16, 37, True)])
def test_apgd_iterates_equal_the_reference_loop(eps, n_iter, random_start):
    f = smooth_nonconvex()
    T0 = torch.rand(SHAPE, generator=torch.Generator().manual_seed(7))
    att = attack("apgd", eps=eps, steps=n_iter, random_start=random_start, seed=11)
    ours, state = run(att, f, T0, n_iter)
    gen = torch.Generator().manual_seed(11) if random_start else None
    ref, ref_best = reference_apgd(f, T0, att.eps, n_iter, rand_gen=gen)
    assert len(state["halvings"]) >= 3, "the test must exercise halving and restarts"
    for k, (a, b) in enumerate(zip(ours[1:], ref), start=1):
        assert torch.equal(a, b), f"iterate {k} differs"
    assert torch.equal(att.final(ours[-1], f(ours[-1])[0], state), ref_best)


def test_apgd_stall_condition_matches_the_reference():
    """Scripted losses: period 1 climbs (no halving); period 2 drops, then climbs
    18 times without beating the best: condition 2 alone halves at 41."""
    n_iter = 100
    rng = np.random.default_rng(0)
    losses = [0.0] + [float(n) for n in range(1, 23)] + [0.0] + \
        [0.5 * n for n in range(1, 19)] + rng.uniform(0, 40, 60).tolist()
    T0 = torch.full(SHAPE, 0.5)
    att = attack("apgd", eps=8, steps=n_iter)
    ours, state = run(att, scripted(losses), T0, n_iter)
    ref, ref_best = reference_apgd(scripted(losses), T0, att.eps, n_iter)
    assert state["halvings"][0] == 41
    for k, (a, b) in enumerate(zip(ours[1:], ref), start=1):
        assert torch.equal(a, b), f"iterate {k} differs"
    assert torch.equal(att.final(ours[-1], losses[n_iter], state), ref_best)


def test_apgd_first_checkpoint_compares_with_the_starting_loss():
    """The deliberate difference: f(x_1) = 5 < f(x_0) = 10 is no increase (paper),
    though 5 > 0 (the reference's unfilled slot). 16 of 22 steps increase: 16 <= 16.5
    halves at 22; the literal reference counts 17 and does not."""
    first = [10.0, 5.0]
    for n in range(2, 23):
        first.append(first[-1] - 0.5 if n in (5, 9, 13, 17, 21) else first[-1] + 1.0)
    losses = first + np.random.default_rng(1).uniform(0, 40, 80).tolist()
    T0 = torch.full(SHAPE, 0.5)
    att = attack("apgd", eps=8, steps=100)
    ours, state = run(att, scripted(losses), T0, 100)
    paper, _ = reference_apgd(scripted(losses), T0, att.eps, 100)
    literal, _ = reference_apgd(scripted(losses), T0, att.eps, 100, literal=True)
    assert state["halvings"][0] == 22
    assert all(torch.equal(a, b) for a, b in zip(ours[1:], paper))
    assert all(torch.equal(a, b) for a, b in zip(ours[1:23], literal[:22]))
    assert not torch.equal(ours[23], literal[22])


def test_apgd_is_invariant_to_adding_a_constant_to_the_loss():
    f = smooth_nonconvex(seed=2)
    T0 = torch.full(SHAPE, 0.5)
    att = attack("apgd", eps=8, steps=40)
    base, _ = run(att, lambda T: (f(T)[0].item(), f(T)[1]), T0, 40)
    shifted, _ = run(att, lambda T: (f(T)[0].item() - 1000.0, f(T)[1]), T0, 40)
    assert all(torch.equal(a, b) for a, b in zip(base, shifted))


# --------------------------------------------------------------------------- known answers

@pytest.mark.parametrize("name", ["pgd", "apgd"])
def test_linear_loss_reaches_the_corner_of_the_eps_ball(name):
    w = torch.randn(SHAPE, generator=torch.Generator().manual_seed(0))
    T0 = torch.full(SHAPE, 0.5)
    att = attack(name, eps=8, steps=10, step_size=2)
    iterates, state = run(att, lambda T: ((w * T).sum(), w), T0, 10)
    corner = T0 + att.eps * torch.sign(w)
    assert torch.equal(iterates[-1], corner)
    assert torch.allclose(corner, 0.5 + torch.sign(w) * 8 / 255, atol=1e-7)
    assert torch.equal(att.final(iterates[-1], (w * corner).sum(), state), corner)


def test_pgd_known_answer_steps():
    G = torch.tensor([1.0, -2.0, 0.0]).expand(SHAPE)
    att = attack("pgd", eps=8, steps=3, step_size=3)
    T, state = att.start(torch.full(SHAPE, 0.5))
    T, state = att.step(T, G, 0.0, state)
    assert torch.equal(T, torch.full(SHAPE, 0.5) + att.step_size * torch.sign(G))
    assert attack("pgd", eps=8, steps=4).step_size == 2.5 * 8 / 4 / 255


def test_mifgsm_normalises_by_l1_and_accumulates_momentum():
    """Step 1: G1 = (1, -3): g1 = (0.25, -0.75), move (+α, -α). Step 2: G2 = (-2, 2):
    g2 = g1 + (-0.5, 0.5) = (-0.25, -0.25), move (-α, -α); PGD would move (-α, +α)."""
    T0 = torch.full((1, 2, 1), 0.5)
    G1 = torch.tensor([1.0, -3.0]).reshape(1, 2, 1)
    G2 = torch.tensor([-2.0, 2.0]).reshape(1, 2, 1)
    att = attack("mifgsm", eps=16, steps=4, step_size=2)
    alpha = att.step_size
    T, state = att.start(T0)
    T, state = att.step(T, G1, 0.0, state)
    assert torch.equal(state["g"].flatten(), torch.tensor([0.25, -0.75]))
    T, state = att.step(T, G2, 0.0, state)
    assert torch.equal(state["g"].flatten(), torch.tensor([-0.25, -0.25]))
    expected = torch.tensor([(0.5 + alpha) - alpha, (0.5 - alpha) - alpha])
    assert torch.allclose(T.flatten(), expected, atol=1e-7)
    assert attack("mifgsm", eps=8, steps=10).step_size == 0.8 / 255


def test_adam_matches_torch_adam_maximising():
    T0 = torch.rand(SHAPE, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.25
    grads = torch.randn((5, *SHAPE), generator=torch.Generator().manual_seed(2))
    att = attack("adam", eps=255, lr=2.0)
    T, state = att.start(T0)
    p = torch.nn.Parameter(T0.clone())
    opt = torch.optim.Adam([p], lr=2.0 / 255, maximize=True)
    for G in grads:
        T, state = att.step(T, G, 0.0, state)
        p.grad = G.clone()
        opt.step()
        with torch.no_grad():
            p.clamp_(0, 1)
        assert torch.equal(T, p.detach())


def test_adam_unbounded_stays_within_the_box():
    T0 = torch.full(SHAPE, 0.5)
    sign = torch.sign(torch.randn(SHAPE, generator=torch.Generator().manual_seed(0)))
    att = attack("adam", eps=255, lr=40.0)
    iterates, _ = run(att, lambda T: ((sign * T).sum(), sign), T0, 30)
    assert all(bool(((X >= 0) & (X <= 1)).all()) for X in iterates)
    assert torch.equal(iterates[-1], (sign + 1) / 2)  # every texel at 0 or 1
    bounded, _ = run(attack("adam", eps=8, lr=40.0), lambda T: ((sign * T).sum(), sign), T0, 5)
    assert float((bounded[-1] - T0).abs().max()) <= 8 / 255 + 1e-7


# --------------------------------------------------------------------------- projection

@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float32, (3, 2, 3), elements=st.floats(-2, 3, width=32)),
       hnp.arrays(np.float32, (3, 2, 3), elements=st.floats(0, 1, width=32)),
       st.floats(0.5, 255))  # ε is at most 255 (undream.spec.limits)
def test_projection_is_the_closest_point_of_ball_and_box(T, T0, eps255):
    T, T0, eps = torch.from_numpy(T), torch.from_numpy(T0), eps255 / 255
    P = project_linf(T, T0, eps)
    lo, hi = torch.clamp(T0 - eps, min=0), torch.clamp(T0 + eps, max=1)
    assert torch.equal(P, torch.min(torch.max(T, lo), hi))
    assert bool(((P >= 0) & (P <= 1)).all())
    assert float((P - T0).abs().max()) <= eps + 1e-6
    assert torch.equal(project_linf(P, T0, eps), P)
    assert torch.equal(attack("pgd", eps=eps255).project(T, T0), P)


# --------------------------------------------------------------------------- visibility

@pytest.mark.parametrize("name", BUILTIN)
@pytest.mark.parametrize("random_start", [False, True])
def test_texels_no_frame_sees_keep_their_value(name, random_start):
    T0 = torch.rand(SHAPE, generator=torch.Generator().manual_seed(4))
    visible = torch.zeros(SHAPE[:2], dtype=torch.bool)
    visible[1:3, :] = True
    f = smooth_nonconvex()

    def masked(T):  # what the renderer gives: zero gradient wherever no frame looks
        loss, G = f(T)
        return loss, G * visible[..., None]

    iterates, _ = run(attack(name, eps=16, steps=12, random_start=random_start), masked, T0, 12,
                      visible=visible)
    for T in iterates:
        assert torch.equal(T[~visible], T0[~visible])
    assert not torch.equal(iterates[-1][visible], T0[visible])


@pytest.mark.parametrize("name", BUILTIN)
def test_zero_gradient_texels_keep_their_value_without_a_mask(name):
    T0 = torch.rand(SHAPE, generator=torch.Generator().manual_seed(5))
    G = torch.randn(SHAPE, generator=torch.Generator().manual_seed(6))
    G[0] = 0.0
    iterates, _ = run(attack(name, eps=16, steps=8), lambda T: ((G * T).sum(), G), T0, 8)
    assert torch.equal(iterates[-1][0], T0[0])


def test_unseen_texels_keep_their_value_whatever_the_attack_does():
    """The step masks any registered attack, even one that moves every texel."""
    @register
    class Drift(Attack):
        name = "test_drift"

        def _step(self, T, G, loss, state):
            return T + 0.01, {}

    try:
        T0 = torch.full(SHAPE, 0.5)
        visible = torch.zeros(SHAPE[:2], dtype=torch.bool)
        visible[0] = True
        G = torch.zeros(SHAPE)
        G[1, 1, 0] = 1.0
        iterates, state = run(attack("test_drift", eps=8), lambda T: (0.0, G), T0, 3,
                              visible=visible)
        seen = visible.clone()
        seen[1, 1] = True
        assert torch.equal(state["visible"], seen)
        assert torch.equal(iterates[-1][~seen], T0[~seen])
        assert torch.allclose(iterates[-1][seen], torch.tensor(0.53), atol=1e-6)
    finally:
        unregister("test_drift")


def test_visible_mask_grows_with_the_texels_seen():
    T0 = torch.full(SHAPE, 0.5)
    visible = torch.zeros(SHAPE[:2], dtype=torch.bool)
    att = attack("pgd", eps=8, steps=1, step_size=1, random_start=True)
    T, state = att.start(T0, visible=visible)
    assert torch.equal(T, T0)
    G = torch.zeros(SHAPE)
    G[2, 3, 1] = 1.0
    T, state = att.step(T, G, 0.0, state)
    assert bool(state["visible"][2, 3]) and int(state["visible"].sum()) == 1
    assert T[2, 3, 1] == 0.5 + att.step_size


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("name", BUILTIN)
def test_non_finite_gradient_never_makes_the_texture_nan(name):
    T0 = torch.full(SHAPE, 0.5)
    att = attack(name, eps=16, steps=5, random_start=True)
    T, state = att.start(T0)
    gen = torch.Generator().manual_seed(0)
    for k, loss in enumerate([1.0, float("nan"), 2.0, float("inf"), 0.5]):
        G = torch.randn(SHAPE, generator=gen)
        G[0, 0, 0], G[1, 1, 1], G[2, 2, 2] = float("nan"), float("inf"), -float("inf")
        if k == 2:
            G[:] = float("nan")
        T, state = att.step(T, G, loss, state)
        assert bool(torch.isfinite(T).all()) and bool(((T >= 0) & (T <= 1)).all())
    assert state["nonfinite"] == 4 * 3 + T.numel()
    assert bool(torch.isfinite(att.final(T, float("nan"), state)).all())


def test_non_finite_gradient_entries_count_as_zero():
    T0 = torch.full(SHAPE, 0.5)
    att = attack("pgd", eps=8, steps=2, step_size=1)
    T, state = att.start(T0)
    G = torch.ones(SHAPE)
    G[0, 0] = torch.tensor([float("nan"), float("inf"), -float("inf")])
    T, state = att.step(T, G, 0.0, state)
    assert torch.equal(T[0, 0], T0[0, 0]) and state["nonfinite"] == 3
    assert bool((T[1:] == 0.5 + att.step_size).all())


def test_bad_textures_gradients_and_states_are_named():
    att = attack("pgd")
    T0 = torch.full(SHAPE, 0.5)
    T, state = att.start(T0)
    bad = T0.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(AttackError, match=r"^T: values must be finite and in \[0, 1\]"):
        att.step(bad, torch.ones(SHAPE), 0.0, state)
    with pytest.raises(AttackError, match=r"^T0: values must be finite"):
        att.start(T0 + 1)
    with pytest.raises(AttackError, match=r"^T0: must be an H×W×C floating tensor"):
        att.start(torch.full((4, 4), 0.5))
    with pytest.raises(AttackError, match=r"^G: must be a tensor shaped like T"):
        att.step(T, torch.ones(4, 4), 0.0, state)
    with pytest.raises(AttackError, match=r"^visible: must be an H×W bool mask"):
        att.start(T0, visible=torch.ones(3, 3, dtype=torch.bool))
    with pytest.raises(AttackError, match=r"^state: made by attack 'pgd', not 'apgd'"):
        attack("apgd").step(T, torch.ones(SHAPE), 0.0, state)
    with pytest.raises(AttackError, match=r"^loss: must be one number"):
        att.step(T, torch.ones(SHAPE), torch.ones(2), state)


# --------------------------------------------------------------------------- state

def assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], torch.Tensor):
            assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
        else:
            assert a[key] == b[key] or (a[key] != a[key] and b[key] != b[key]), key


@pytest.mark.parametrize("name", BUILTIN)
def test_state_json_round_trip_gives_the_identical_next_step(name):
    f = smooth_nonconvex()
    T0 = torch.rand(SHAPE, generator=torch.Generator().manual_seed(8))
    att = attack(name, eps=8, steps=20, random_start=True)
    iterates, state = run(att, f, T0, 3)
    T = iterates[-1]
    restored = state_from_dict(json.loads(json.dumps(state_to_dict(state), allow_nan=False)))
    assert_same_state(restored, state)
    loss, G = f(T)
    T_a, s_a = att.step(T, G, loss, state)
    T_b, s_b = att.step(T, G, loss, restored)
    assert torch.equal(T_a, T_b)
    assert_same_state(s_a, s_b)


def test_apgd_state_keeps_non_finite_losses_in_strict_json():
    att = attack("apgd", steps=10)
    T, state = att.start(torch.full(SHAPE, 0.5))
    T, state = att.step(T, torch.ones(SHAPE), float("nan"), state)
    assert state["loss_best"] == -math.inf
    text = json.dumps(state_to_dict(state), allow_nan=False)
    assert state_from_dict(json.loads(text))["loss_best"] == -math.inf


@pytest.mark.parametrize("name", BUILTIN)
def test_step_does_not_mutate_its_arguments(name):
    f = smooth_nonconvex()
    att = attack(name, eps=8, steps=10)
    iterates, state = run(att, f, torch.full(SHAPE, 0.5), 2)
    T = iterates[-1]
    loss, G = f(T)
    copies = (T.clone(), G.clone(), {k: v.clone() if isinstance(v, torch.Tensor) else v
                                      for k, v in state.items()})
    first = att.step(T, G, loss, state)
    assert torch.equal(T, copies[0]) and torch.equal(G, copies[1])
    assert_same_state(state, copies[2])
    assert torch.equal(att.step(T, G, loss, state)[0], first[0])


# --------------------------------------------------------------------------- frames

def test_frame_batch_is_seeded_per_iteration():
    a = frame_batch(50, 8, iteration=3, seed=1)
    assert a == frame_batch(50, 8, iteration=3, seed=1)
    assert a == sorted(set(a)) and len(a) == 8 and all(0 <= i < 50 for i in a)
    assert a != frame_batch(50, 8, iteration=4, seed=1)
    assert a != frame_batch(50, 8, iteration=3, seed=2)
    assert frame_batch(5, None, 0, 0) == frame_batch(5, 9, 0, 0) == [0, 1, 2, 3, 4]
    with pytest.raises(AttackError, match="batch_size must be None or an integer >= 1"):
        frame_batch(5, 0, 0, 0)
    with pytest.raises(AttackError, match="n_frames must be an integer >= 1"):
        frame_batch(0, 2, 0, 0)


def test_average_frames_drops_non_finite_frames():
    g = [torch.full(SHAPE, 1.0), torch.full(SHAPE, float("nan")), torch.full(SHAPE, 3.0),
         torch.full(SHAPE, 5.0)]
    G, loss, kept = average_frames(g, [1.0, 2.0, 3.0, float("inf")])
    assert kept == [0, 2] and loss == 2.0 and torch.equal(G, torch.full(SHAPE, 2.0))
    with pytest.raises(AttackError, match="all 2 frames have a non-finite"):
        average_frames(g[1:2] * 2, [1.0, 1.0])
