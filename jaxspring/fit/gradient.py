"""The gradient stage's pieces: the optimiser step, the stop rules, the best point kept, and
the retreat off the stability wall.

**Step.** One optimiser step of a stage (optax's L-BFGS or Adam), batched over the members of a
fit with `vmap`.

**Stop rules.** When a stage has converged (the rules of `FitSettings`).

**Best point.** Never worse than given: each stage ends on the best point it has seen, a plan on
the best of its stages.

**Retreat.** Where an L-BFGS stage stops early, a step to softer values and a
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

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..sim.params import NON_NEGATIVE, split_name
from .least_squares import LM_REMAINING, LM_WINDOW
from .progress import FitProgress
from .settings import FitSettings


def _optimizer(settings: FitSettings):
    if settings.optimizer != "adam":  # "auto" and "lm" stages without a least-squares loss: L-BFGS
        return optax.lbfgs()
    return optax.chain(optax.clip_by_global_norm(settings.clip), optax.adam(settings.learning_rate))


def _strong(leaf):
    leaf = jnp.asarray(leaf)
    return jax.lax.convert_element_type(leaf, leaf.dtype) if leaf.weak_type else leaf


def step_function(loss, settings: FitSettings, data_batched: bool):
    """(step, init, value) of the optimiser on `loss(theta, data)`, each over the members
    (`data` shared, or one per member with `data_batched`): `step(theta, opt_state, data)`
    -> (theta, opt_state, loss before the step), `init(theta)`, `value(theta, data)`."""
    optimizer = _optimizer(settings)

    def single(theta, opt_state, data):
        value_fn = lambda th: loss(th, data)  # noqa: E731
        if settings.optimizer != "adam":
            value, grad = optax.value_and_grad_from_state(value_fn)(theta, state=opt_state)
            updates, opt_state = optimizer.update(grad, opt_state, theta, value=value, grad=grad, value_fn=value_fn)
        else:
            value, grad = jax.value_and_grad(value_fn)(theta)
            updates, opt_state = optimizer.update(grad, opt_state, theta)
        return optax.apply_updates(theta, updates), opt_state, value

    step = jax.jit(jax.vmap(single, in_axes=(0, 0, 0 if data_batched else None)))
    # strong dtypes: an optimizer state whose leaves start weakly typed (optax's line-search
    # info) comes back strongly typed from the first step, and the step would compile twice
    init = jax.jit(jax.vmap(lambda theta: jax.tree_util.tree_map(_strong, optimizer.init(theta))))
    value = jax.jit(jax.vmap(loss, in_axes=(0, 0 if data_batched else None)))
    return step, init, value


def finite_losses(loss) -> np.ndarray:
    """`loss` as floats, every non-finite value (a rollout that blew up) as infinity, so it ranks last."""
    loss = np.asarray(loss, dtype=float)
    return np.where(np.isfinite(loss), loss, np.inf)


def where_members(mask, a, b):
    """Per member (leading axis): `a` where `mask` (B,) holds, else `b`."""
    return jnp.where(jnp.asarray(mask).reshape((-1,) + (1,) * (jnp.ndim(b) - 1)), a, b)


def keep_best_of_stage(progress: FitProgress, names, step, opt_state, data) -> tuple[bool, np.ndarray | None]:
    """End a stage on the best point it has seen on its own loss (per member): the point it
    stopped at, or an earlier one with a lower loss (Adam's and the ensemble's losses are not
    monotone). Taken from the history, so a resumed fit chooses as an uninterrupted one.
    Returns whether any member went back, and the stage's loss where each member ends (None
    for a stage without iterations or with a fitted start)."""
    done = [i for i, s in enumerate(progress.stage_of_iteration) if s == progress.stage]
    if not done or set(progress.theta) != set(names):  # a fitted start has no history: polished after
        return False, None
    _, _, end = step(progress.theta, opt_state, data)  # the loss where the stage stopped
    losses = np.stack([np.asarray(progress.loss[i], dtype=float) for i in done])
    losses = finite_losses(losses)
    best = np.argmin(losses, axis=0)
    members = np.arange(losses.shape[1])
    end = finite_losses(end)
    back = losses[best, members] < end
    if not back.any():
        return False, end
    theta = {}
    for n, value in progress.theta.items():
        value = np.array(value)
        if n in names:
            for m in np.nonzero(back)[0]:
                value[m] = np.log(progress.values[n][done[best[m]]][m])
        theta[n] = jnp.asarray(value)
    progress.theta = theta
    return True, np.where(back, losses[best, members], end)


def best_of_stages(progress: FitProgress, names, value, data):
    """(theta, loss) per member: the best on the final objective of where each stage began
    (the first, the start values) and where the last one ended, so a plan never returns a
    point worse than one it passed through (a whole-horizon stage can walk away from a
    shooting answer)."""
    theta = progress.theta
    loss = np.asarray(value(theta, data), dtype=float)
    if set(theta) != set(names):  # a fitted start: the start state's history is not kept
        return theta, loss
    firsts = sorted({progress.stage_of_iteration.index(s) for s in set(progress.stage_of_iteration)})
    for i in firsts:
        candidate = {n: jnp.asarray(np.log(np.asarray(progress.values[n][i]))) for n in names}
        candidate_loss = np.asarray(value(candidate, data), dtype=float)
        better = np.isfinite(candidate_loss) & ((candidate_loss < loss) | ~np.isfinite(loss))
        if better.any():
            theta = {n: where_members(better, candidate[n], theta[n]) for n in names}
            loss = np.where(better, candidate_loss, loss)
    return theta, loss


def converged(progress: FitProgress, settings: FitSettings, final_stage: bool, opt_state, floor: float) -> bool:
    """Whether every member has converged in the current stage (see FitSettings). An ensemble
    stage says so itself, or stops when it fits its target to round-off (`floor`, the loss of
    positions that differ by round-off): without noise its cloud would otherwise shrink
    towards standard errors of zero for all its iterations. Gradient stages stop on their
    steps and loss alone, which reach further than that floor (in float32 by far)."""
    if isinstance(opt_state, dict) and "done" in opt_state:  # an ensemble stage
        current = progress.loss and progress.stage_of_iteration[-1] == progress.stage
        return bool(np.all(np.asarray(opt_state["done"]) > 0) or (current and np.all(progress.loss[-1] <= floor)))
    in_stage = [loss for loss, s in zip(progress.loss, progress.stage_of_iteration) if s == progress.stage]
    if isinstance(opt_state, dict) and "remaining" in opt_state:  # Levenberg-Marquardt (least_squares)
        if np.all(np.asarray(opt_state["remaining"]) < LM_REMAINING):
            return True
        if len(in_stage) > LM_WINDOW:  # less than one unit of the residuals' variance in LM_WINDOW iterations
            before, now = np.asarray(in_stage[-1 - LM_WINDOW]), np.asarray(in_stage[-1])
            if np.all((before - now) * np.asarray(opt_state["dof"]) / np.maximum(now, 1e-300) < 1.0):
                return True
    if progress.last_step is not None:
        limit = settings.step_tolerance if final_stage else settings.warmup_step_tolerance
        if np.all(progress.last_step <= limit):
            return True
    if len(in_stage) < 2:
        return False
    first, now = np.asarray(in_stage[0]), np.asarray(in_stage[-1])
    if np.all(now <= settings.tolerance**2 * first):
        return True
    if len(in_stage) < 6 or settings.optimizer == "adam":  # Adam's loss is not monotone
        return False
    before = np.asarray(in_stage[-6])
    return bool(np.all((before - now) <= settings.tolerance * np.abs(before)))


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
