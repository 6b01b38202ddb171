"""Render seeds: one per (run seed, iteration, frame), so any process renders a frame alike."""
from __future__ import annotations


def frame_seed(run_seed: int, iteration: int, frame: int) -> int:
    """A render seed unique to (run, iteration, frame); ``seed + 1`` is its ``seed_grad``."""
    return (run_seed * 1_000_003 + iteration * 10_007 + frame * 2) % (2**31 - 2)
