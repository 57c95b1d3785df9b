"""Levenberg-Marquardt on a few parameter values, and the shooting stage's finish with it.

A first-order optimiser sees the loss, a sum of squares, and its line search compares loss
values; near the answer their differences drown in the round-off of the simulated positions
(in float32, along the jelly's valley of stiffness against damping, L-BFGS stalls with its
damping 13% off, at a loss of 1e-10 m^2 that looks converged). Gauss-Newton sees the residuals
and their Jacobian, whose round-off enters a step linearly and averages out: from the same
point three steps take the damping to 1.4e-5 of the truth. So a stage whose objective is a
least-squares misfit over short segments (multiple shooting from recorded states, where the
misfit stays smooth) and whose optimiser stalled within round-off's reach (`FINISH_BELOW`)
ends with Levenberg-Marquardt steps (`finish_shooting_stage`, `finish_segments`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..sim.sharding import shard_batch
from .horizon import round_off_loss
from .objective import segment_misfit_function, stage_residual_function, target_data
from .progress import FitProgress
from .recordings import RecordingTarget

MAX_VALUES = 64
"""Levenberg-Marquardt takes a column of the Jacobian per fitted value: with more values than
this a stage ends on its first-order optimiser alone."""

FINISH_BELOW = 4.0
"""A shooting stage whose optimiser stalled (its line search found no lower loss twice: the
values did not move) is finished when its misfit is below this many round-off losses
(`horizon.round_off_loss`, positions 64 units of round-off of their size apart; RMS
residuals up to 128 units): exact data, where round-off, not the data, limits a line search.
Measured on the 0.7 s jelly: float32's L-BFGS stalls at 0.04 of it with kd 13% off;
float64's converges on its own (its last steps shrink, not vanish; finishing it anyway took
a 2.5 s jelly draw from 2.7e-11 to 1.3e-13 and from 23 to 28 s, the next stage's line
searches then starting at round-off).
With 1% noise the misfit is the noise's, 1e5 of it in float32 and far more in float64,
and the optimiser's answer is as good as the noisy segments allow: finishing those exactly
(they start from noisy recorded states, so their least-squares answer is itself biased)
made the whole-horizon stage after it end farther off (over 10 noise seeds, float64: kd
8.9% off in the median against 5.4%, 2 s slower)."""


@dataclasses.dataclass
class Solution:
    """A Levenberg-Marquardt solve: `history` holds (cost / residual count, flat values) before
    each accepted step; `flat` and `loss` (cost / residual count) are where it ended."""

    history: list
    flat: np.ndarray
    loss: float


def levenberg_marquardt(
    residual, jacobian, flat, iterations: int, step_tolerance: float, tolerance: float, gradient=None
):
    """Minimise |r|^2 from `flat`, with residual(flat) -> r (n,) and jacobian(flat) -> J (n, P),
    by steps that only go downhill, damped in the scale of J^T J's diagonal (so invariant to
    the values' scales). Returns a `Solution`.

    With `gradient(flat)` -> J^T r taken exactly (reverse mode), `jacobian` may be an
    approximation: it shapes the steps (J^T J), not where they end (where J^T r vanishes).

    Ends after `iterations` accepted steps, when a step would move no value by more than
    `step_tolerance` (not taken: converged; an answer already at round-off is left as it is,
    where a step of round-off would only make the next optimiser's line search work longer),
    when a step lowers the cost by less than `tolerance`^2 of it, or when twelve dampings,
    each ten times the last, find no lower cost.
    Normal equations are solved in float64 whatever the residuals' precision.

    Example:
        >>> levenberg_marquardt(lambda p: p - 1.0, lambda p: np.eye(2), np.zeros(2), 10, 1e-9, 1e-9).flat
        array([1., 1.])
    """
    dtype = np.asarray(flat).dtype
    flat = np.asarray(flat)
    r = np.asarray(residual(flat), dtype=float)
    cost = float(r @ r)
    history = []
    damping = 1e-3
    for _ in range(iterations):
        if not np.isfinite(cost) or cost == 0.0:
            break
        jac = np.asarray(jacobian(flat), dtype=float)
        slope = jac.T @ r if gradient is None else np.asarray(gradient(flat), dtype=float)
        normal = jac.T @ jac
        scale = np.maximum(np.diag(normal), 1e-300)
        accepted = False
        for _ in range(12):
            step = -np.linalg.pinv(normal + damping * np.diag(scale), rcond=1e-14) @ slope
            if np.max(np.abs(step)) <= step_tolerance:  # converged: not taken
                break
            candidate = (flat + step).astype(dtype)
            r_new = np.asarray(residual(candidate), dtype=float)
            cost_new = float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                accepted = True
                break
            damping *= 10.0
        if not accepted:
            break
        history.append((cost / r.size, flat))
        improvement = (cost - cost_new) / cost
        flat, r, cost = candidate, r_new, cost_new
        damping = max(damping / 10.0, 1e-12)
        if improvement <= tolerance**2:
            break
    return Solution(history, flat, cost / max(r.size, 1))


LM_REMAINING = 0.01
"""A Levenberg-Marquardt stage has converged when the Gauss-Newton model predicts less than this
decrease of the sum of squares, in units of the residuals' variance, down to its minimum:
the values are then within a tenth of a standard error of it, closer than the data decide."""

LM_WINDOW = 5
"""Iterations over which a Levenberg-Marquardt stage must lower the sum of squares by one unit
of the residuals' variance to go on."""

LM_LEAST_SCALE = 1e-6
"""The least damping scale of a value, relative to the largest diagonal entry of J^T J."""

LM_LARGEST_STEP = 6.907755278982137
"""The most one Levenberg-Marquardt iteration moves a log value (ln 1000: a factor of 1000); a
longer step is shortened as a whole: a value the residuals hardly see is never thrown to 0 or
to infinity."""

LM_TRIALS = 12
"""Dampings tried in one Levenberg-Marquardt iteration, each ten times the last, before the
iteration gives up (the point stays; the stage's stop rules then end it)."""


def lm_step_function(residual, data_batched: bool):
    """(step, init) of Levenberg-Marquardt as a fit stage's optimiser, over the members like
    `gradient.step_function`: `step(theta, state, data)` -> (theta, state, loss before the
    step), the loss being |residual|^2. One iteration takes the Jacobian of the residuals with
    respect to the log values (jacfwd: one column per value) and tries dampings (in the scale
    of J^T J's diagonal, so invariant to the values' scales) from the state's, ten times more
    each, until the loss is lower (at most `LM_TRIALS`); the next iteration starts from a
    tenth of the damping that worked. The state holds the damping and `remaining`: the
    decrease of the loss that the Gauss-Newton model predicts down to its minimum, in units of
    the residuals' variance (|r|^2 / `dof`, dof = n - P); the stage has converged when that is
    below `LM_REMAINING`, or when its last `LM_WINDOW` iterations lowered the loss by less than
    one such unit together (`gradient.converged`): on recordings the misfit is model error, and
    rough at scales the data do not decide. The state is saved with a checkpoint, so a resumed
    stage goes on as an uninterrupted one.

    For a few values and many residuals (recordings) an iteration costs about a rollout per
    value (forward mode) and a trial or two, and far fewer rollouts are needed than with
    L-BFGS's line searches (docs/performance.md, fit speed).
    """

    def single(theta, state, data):
        flat, unravel = ravel_pytree(theta)
        r_of = lambda f: residual(unravel(f), data)  # noqa: E731
        r = r_of(flat)
        cost = jnp.sum(r**2)
        jac = jax.jacfwd(r_of)(flat)
        normal, slope = jac.T @ jac, jac.T @ r
        # damping in each value's own scale, but not below LM_LEAST_SCALE of the largest: a value
        # the residuals hardly see would take nearly undamped steps
        scale = jnp.maximum(jnp.diag(normal), jnp.maximum(LM_LEAST_SCALE * jnp.max(jnp.diag(normal)), 1e-300))
        # the Gauss-Newton model's decrease to its minimum, g^T (J^T J)^-1 g, in units of the
        # residuals' variance (the unseen coordinates' residuals are exactly zero: not counted)
        unit = jnp.sqrt(scale)
        newton = jnp.linalg.pinv(normal / jnp.outer(unit, unit), rtol=1e-12) @ (slope / unit)
        dof = jnp.maximum(jnp.sum(r != 0) - flat.size, 1)
        variance = cost / dof
        remaining = jnp.dot(slope / unit, newton) / jnp.maximum(variance, 1e-300)

        def trial(carry):
            damping, _, _, tries = carry
            step = -jnp.linalg.solve(normal + damping * jnp.diag(scale), slope)
            step = step * jnp.minimum(1.0, LM_LARGEST_STEP / jnp.max(jnp.abs(step)))
            candidate = flat + step
            new = jnp.sum(r_of(candidate) ** 2)
            better = jnp.isfinite(new) & (new < cost) & jnp.all(jnp.isfinite(step))
            return jnp.where(better, damping, damping * 10.0), candidate, better, tries + 1

        def more(carry):
            return ~carry[2] & (carry[3] < LM_TRIALS)

        start = (state["damping"], flat, jnp.asarray(False), jnp.asarray(0))
        damping, candidate, better, _ = jax.lax.while_loop(more, trial, start)
        ahead = jnp.where(better, jnp.maximum(damping / 10.0, 1e-12), damping)
        flat = jnp.where(better, candidate, flat)
        return unravel(flat), {"damping": ahead, "remaining": remaining, "dof": dof.astype(cost.dtype)}, cost

    step = jax.jit(jax.vmap(single, in_axes=(0, 0, 0 if data_batched else None)))

    def init(theta):
        members = jax.tree_util.tree_leaves(theta)[0].shape[0]
        dtype = jax.tree_util.tree_leaves(theta)[0].dtype
        return {
            "damping": jnp.full((members,), 1e-3, dtype=dtype),
            "remaining": jnp.full((members,), jnp.inf, dtype=dtype),
            "dof": jnp.ones((members,), dtype=dtype),
        }

    return step, init


def least_squares_residual(scene, target, names, stage, settings, theta: dict):
    """The residual of a stage whose optimiser is Levenberg-Marquardt, else None: with
    `settings.optimizer` "lm", or "auto" on recordings, for a "direct" stage of a
    least-squares loss (`objective.stage_residual_function`) of at most `MAX_VALUES` values."""
    wanted = settings.optimizer == "lm" or (settings.optimizer == "auto" and isinstance(target, RecordingTarget))
    if not wanted or set(theta) != set(names):  # fitted start states: too many columns
        return None
    if sum(int(np.prod(np.shape(theta[n])[1:])) for n in names) > MAX_VALUES:
        return None
    return stage_residual_function(scene, target, names, stage)


def stage_optimizer(settings, residual) -> str:
    """The optimiser a stage runs: "lm" where it has a least-squares `residual`
    (`least_squares_residual`), else "adam" if asked for, else "lbfgs"."""
    return "lm" if residual is not None else "adam" if settings.optimizer == "adam" else "lbfgs"


def finish_shooting_stage(
    scene, observations: list, names, segment: int, settings, progress: FitProgress, loss, sharded: bool
):
    """End a shooting stage (segments of `segment` frames from recorded states) with
    Levenberg-Marquardt on its residuals (`finish_segments`) for the members whose optimiser
    `stalled` with their misfit (`loss`, (B,): the stage's loss where each ended it) within
    round-off's reach. The steps join the stage's history in `progress` as iterations (a
    member that stops early repeats its answer) and its answers replace `progress.theta`
    (placed on the devices again when the members are `sharded`).

    Example:
        >>> finish_shooting_stage(scene, [obs], ["ks", "kd"], 10, js.FitSettings(), progress, loss, False)
    """
    halted = stalled(progress)
    if halted is None or not halted.any():
        return
    found = finish_segments(scene, observations, names, segment, progress.theta, settings, loss, halted)
    if found is None:
        return
    solutions, unravel = found
    values = lambda flat: {n: np.exp(np.asarray(x)) for n, x in unravel(jnp.asarray(flat)).items()}  # noqa: E731
    for i in range(max(len(s.history) for s in solutions)):
        rows = [s.history[i] if i < len(s.history) else (s.loss, s.flat) for s in solutions]
        progress.loss.append(np.array([cost for cost, _ in rows]))
        points = [values(flat) for _, flat in rows]
        for n in names:
            progress.values[n].append(np.stack([p[n] for p in points]))
        progress.stage_of_iteration.append(progress.stage)
        progress.iteration += 1
    answers = [unravel(jnp.asarray(s.flat)) for s in solutions]
    theta = dict(progress.theta)
    for n in names:
        theta[n] = jnp.stack([a[n] for a in answers]).astype(progress.theta[n].dtype)
    progress.theta = shard_batch(theta) if sharded else theta


def stalled(progress: FitProgress) -> np.ndarray | None:
    """Per member, whether the stage's last two iterations left every value where it was: the
    optimiser's line search found no lower loss (None: fewer than two iterations).

    Example:
        >>> stalled(progress)  # array([ True, False]): the first member's line search stalled
    """
    return None if progress.last_step is None else np.asarray(progress.last_step) == 0


def finish_segments(scene, observations: list, names, segment: int, theta: dict, settings, misfits=None, halted=None):
    """Levenberg-Marquardt on the misfit of `segment`-frame segments from recorded states
    (the "shooting" stage's objective), from `theta` (name -> log values, (B, ...)), for each
    member of the batch (`observations` one target shared, or one per member): at most
    `settings.polish_iterations` steps, ending as `levenberg_marquardt` does with the
    settings' `step_tolerance` and `tolerance`. A member is left where it is (a Solution
    without steps) unless its optimiser stalled (`halted`, (B,) bools; None: every member)
    with its misfit (`misfits`, (B,): the stage's loss there, so nothing is compiled for a
    member left alone; None: evaluated here) below `FINISH_BELOW` round-off losses.

    Returns (a Solution per member, unravel: its flat log values -> name -> log value), or
    None when more than `MAX_VALUES` values are fitted.

    Example:
        >>> solutions, unravel = finish_segments(scene, [obs], ["ks", "kd"], 10, theta, js.FitSettings())
        >>> unravel(solutions[0].flat)  # name -> log value, finished where in reach
    """
    flat, unravel = ravel_pytree({n: jnp.asarray(theta[n][0]) for n in names})
    if flat.shape[0] > MAX_VALUES:
        return None
    residual, jacobian, gradient = segment_least_squares(scene, observations[0], names, segment, unravel, flat.shape[0])
    solutions = []
    for m in range(np.shape(theta[names[0]])[0]):
        target = observations[m if len(observations) > 1 else 0]
        data = target_data(target)
        start = np.asarray(ravel_pytree({n: jnp.asarray(theta[n][m]) for n in names})[0])
        if halted is not None and not halted[m]:
            solutions.append(Solution([], start, np.nan if misfits is None else float(misfits[m])))
            continue
        if misfits is None:
            misfit = float(np.mean(np.asarray(residual(start, data), dtype=float) ** 2))
        else:
            misfit = float(np.asarray(misfits, dtype=float)[m])
        if not misfit <= FINISH_BELOW * round_off_loss(scene, target):
            solutions.append(Solution([], start, misfit))
            continue
        solutions.append(
            levenberg_marquardt(
                lambda v, d=data: residual(v, d),
                lambda v, d=data: jacobian(v, d),
                start,
                settings.polish_iterations,
                settings.step_tolerance,
                settings.tolerance,
                gradient=lambda v, d=data: gradient(v, d),
            )
        )
    return solutions, unravel


def segment_least_squares(scene, observations, names, segment: int, unravel, size: int):
    """(residual, jacobian, gradient), each (flat, data) -> array and compiled: the misfit of
    `segment`-frame segments from recorded states as a flat vector (n,), an approximation of
    its Jacobian (n, P) in the flat log values (`unravel` turns `size` of them into name ->
    log value), and the exact J^T r (reverse mode).

    The Jacobian is taken by central differences, with steps of eps^(1/3) in log space
    (`difference_step`), the 2 P points one after the other (`lax.map`: one rollout's
    memory, as the stage's own): the stage's own simulation serves (the native kernels are
    reverse-mode only), where a forward-mode Jacobian would compile the pure-JAX step for
    seconds (measured on the jelly: 0.14 s against 2.9 s). In float64 it is good to a few
    1e-6 of a column's size (the chain's); in float32 a weakly determined column (the
    jelly's damping) can be tens of percent off. With the exact J^T r that changes the
    steps, not where they converge (where J^T r vanishes).

    Example:
        >>> flat, unravel = ravel_pytree({"ks": jnp.log(250.0), "kd": jnp.log(0.05)})
        >>> residual, jacobian, gradient = segment_least_squares(scene, obs, ["ks", "kd"], 10, unravel, 2)
        >>> jacobian(flat, target_data(obs)).shape  # (residuals, 2)
    """
    misfit = segment_misfit_function(scene, observations, names, segment)
    residual_of = lambda vector, data: misfit(unravel(vector), data).reshape(-1)  # noqa: E731
    h = difference_step(scene.model.mass.dtype)
    offsets = np.concatenate([np.eye(size), -np.eye(size)]) * h

    @jax.jit
    def jacobian(vector, data):
        points = vector + offsets.astype(vector.dtype)
        r = jax.lax.map(lambda point: residual_of(point, data), points)
        return ((r[:size] - r[size:]) / jnp.diagonal(points[:size] - points[size:])[:, None]).T  # steps as rounded

    gradient = jax.jit(jax.grad(lambda vector, data: 0.5 * jnp.sum(residual_of(vector, data) ** 2)))
    return jax.jit(residual_of), jacobian, gradient


def difference_step(dtype) -> float:
    """Central differences' step for a smooth function in `dtype`: eps^(1/3) balances the
    truncation error (h^2) against round-off (eps / h).

    Example:
        >>> difference_step(jnp.float64)  # 6.06e-06
    """
    return float(jnp.finfo(dtype).eps) ** (1 / 3)
