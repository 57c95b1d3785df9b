"""Off the stability wall: where an L-BFGS stage stops early, a step to softer values and a
fresh start of its memory.

An explicit time step simulates stiffness, damping and drag only up to a limit; past it a
rollout's fastest mode grows. On recordings the model cannot fit exactly, the best misfit
often lies at the foot of that wall (the cable benchmark's does: 10% more stretch stiffness
quadruples the misfit there). A stage that arrives *on* the wall stalls: the gradient of a
rollout whose fastest mode grows is dominated by that growth and points the wrong way.
Measured on the cable benchmark (8 x 500 frames, a start search's point at ks.stretch 8062,
kd.stretch 6.45): the loss rose along the negative gradient at every step length from 1e-4 to
2 (in log values), L-BFGS stopped after 6 iterations at 60.9 mm^2. Every stiffness, damping
and drag value 3% lower, the loss was 53.2 mm^2 with a gradient 1e7 times smaller, and a fresh
L-BFGS from there went on to 42.6 mm^2, the best point known.

So when an L-BFGS stage stops before its iteration budget, the loss at `RETREAT_FACTORS` times
every such value (one point per factor) is compared with the loss where it stopped; a member
for which one is lower by `RETREAT_GAIN` of it or more goes on from the lowest,
with a fresh optimizer memory, at most `RETREATS` times per stage. Softer values only slow
the fastest motion, so they are on the simulable side of the wall. At an interior minimum
no such point is lower and the stage ends as before, at the price of a few rollouts.
"""

from __future__ import annotations

import math

import numpy as np

from ..sim.params import NON_NEGATIVE, split_name
from .best_point import finite_losses, where_members
from .results import FitProgress

RETREAT_FACTORS = (0.97, 0.9)
"""Factors tried on every stiffness, damping and drag value where a stage stops early."""
RETREATS = 3
"""Restarts from a softer point allowed per stage."""
RETREAT_GAIN = 0.01
"""Least relative loss decrease at a softer point that restarts a member (a stage that stopped
short of an interior minimum by less is left alone)."""


def soft_names(names) -> list[str]:
    """The fitted names whose lower values slow the fastest motion (stiffness, damping, drag)."""
    return [n for n in names if split_name(n)[0] in NON_NEGATIVE]


def retreat(progress: FitProgress, names, value, data) -> np.ndarray:
    """Move each member whose loss is lower at a softer point (module docstring) there.

    `progress.theta` holds log values (members first); `value(theta, data)` is the stage's
    loss per member. Returns the members moved, (B,) bool; `progress.theta` is updated
    (the other entries of theta, a fitted start state for one, are kept)."""
    soft = soft_names(names)
    current = finite_losses(value(progress.theta, data))
    if not soft:
        return np.zeros(current.shape, bool)
    best_loss, best = current.copy(), dict(progress.theta)
    for factor in RETREAT_FACTORS:
        trial = {n: v + math.log(factor) if n in soft else v for n, v in progress.theta.items()}
        loss = finite_losses(value(trial, data))
        lower = (loss < best_loss) & (loss <= (1 - RETREAT_GAIN) * current)
        if lower.any():
            best = {n: where_members(lower, trial[n], v) for n, v in best.items()}
            best_loss = np.where(lower, loss, best_loss)
    moved = best_loss < current
    if moved.any():
        progress.theta = best
    return moved
