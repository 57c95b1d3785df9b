"""Never worse than given: each stage ends on the best point it has seen, a plan on the best of its stages."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .results import FitProgress


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
