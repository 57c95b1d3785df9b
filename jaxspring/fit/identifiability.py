"""Gauss-Newton polish and the identifiability report (standard errors, correlations, warnings)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..sim.scene import Scene
from .least_squares import MAX_VALUES, levenberg_marquardt
from .objective import residual_function, segment_misfit_function, target_data
from .observations import Observations


@dataclasses.dataclass(frozen=True)
class Identifiability:
    """Gauss-Newton uncertainty at the optimum.

    Attributes:
        standard_error: name -> standard error of the parameter (same units).
        relative_standard_error: name -> standard error / value.
        correlation: (P, P) correlation matrix of the (log) parameters, in `names` order.
        names: parameter names of the correlation matrix's rows.
        noise_std: residual standard deviation [m] used for the estimate.
        warnings: plain-language warnings (not identifiable, poorly determined, confounded).
        objective: what the fitted values minimise, in words (the standard errors are its).
    """

    standard_error: dict
    relative_standard_error: dict
    correlation: np.ndarray
    names: tuple
    noise_std: float
    warnings: tuple
    objective: str = "the misfit over the whole horizon"

    def covariance(self) -> dict:
        """{"names": labels, "matrix": (P, P)}: the covariance of the log parameter values
        (what `js.predict` draws its bands from).

        Example:
            >>> js.predict(scene, result.final, recs, covariance=result.identifiability.covariance())
        """
        relative = np.concatenate(
            [np.asarray(self.relative_standard_error[n], dtype=float).reshape(-1) for n in unique_names(self.names)]
        )
        return {"names": list(self.names), "matrix": self.correlation * np.outer(relative, relative)}


def unique_names(labels) -> list[str]:
    """Parameter names of labels, in order ("cd", "m[0]", "m[1]" -> "cd", "m")."""
    names = []
    for label in labels:
        name = label.split("[")[0]
        if name not in names:
            names.append(name)
    return names


class _PolishSteps(list):
    """(loss, values) before each accepted Gauss-Newton step, plus the final values and loss."""

    final: dict
    final_loss: float


def gauss_newton_polish(scene, observations, names, values, settings, max_parameters: int = MAX_VALUES, segment=None):
    """Levenberg-Marquardt on the full-horizon residuals (with `segment`, on segments of that
    many frames from recorded states), from the first-order optimiser's answer.

    Least squares with few parameters is what Gauss-Newton is for: it is invariant to the
    parameters' scales, so it finishes a flat, badly scaled valley (the jelly's damping
    against its stiffness) where a first-order method crawls.
    """
    flat, unravel, residuals = residual_function(scene, observations, names, values, segment)
    if flat.shape[0] > max_parameters:
        return []
    solution = levenberg_marquardt(
        jax.jit(residuals),
        jax.jit(jax.jacfwd(residuals)),
        np.asarray(flat),
        settings.polish_iterations,
        settings.step_tolerance,
        settings.tolerance,
    )
    to_values = lambda v: {n: np.asarray(jnp.exp(x)) for n, x in unravel(jnp.asarray(v)).items()}  # noqa: E731
    steps = _PolishSteps((loss, to_values(v)) for loss, v in solution.history)
    steps.final = to_values(solution.flat)
    steps.final_loss = solution.loss
    return steps


def start_polish(scene, target, names, values, nuisance, settings):
    """Levenberg-Marquardt on the parameters and every recording's start state (and driven
    paths, with `fit_driven`) together (`block_lm`: each recording's own unknowns are
    eliminated each step), from the first-order optimiser's answer and `nuisance`
    ({"start": ..., "driven": ...}); steps only downhill. Returns polish steps with
    `.final`, `.final_loss`, `.nuisance` (same keys), `.unknowns` (how many were
    estimated) and `.reduced` (the parameters' normal matrix with them estimated, for
    the standard errors)."""
    from .block_lm import block_levenberg_marquardt
    from .recording_loss import block_problem

    p0, unravel, s0, residual, data, to_nuisance = block_problem(scene, target, names, values, nuisance)
    solution = block_levenberg_marquardt(
        residual, p0, s0, data, iterations=max(settings.polish_iterations, 30), tolerance=settings.step_tolerance
    )
    count = max(target.residual_count, 1)
    to_values = lambda v: {n: np.asarray(jnp.exp(x)) for n, x in unravel(jnp.asarray(v)).items()}  # noqa: E731
    steps = _PolishSteps((cost / count, to_values(p)) for cost, p in solution.history)
    steps.final, steps.final_loss = to_values(solution.p), solution.cost / count
    steps.nuisance, steps.reduced = to_nuisance(solution.s), solution.reduced
    unseen_padding = (
        3 * len(target.driven) * int(np.sum(target.frame_count - target.lengths)) if target.fit_driven else 0
    )
    steps.unknowns = int(s0.size) - unseen_padding
    return steps


def identifiability(scene: Scene, observations: Observations, names, values: dict, *, max_parameters: int = 64):
    """Gauss-Newton standard errors and correlations of `values` (parameter name -> value)
    for the whole-horizon fit of `observations`, with warnings where the data do not
    determine a parameter; None when there are more than `max_parameters` values.

    Example:
        >>> report = js.identifiability(scene, obs, ["ks", "kd"], result.final)
        >>> report.standard_error["ks"], report.warnings
    """
    return identifiability_report(scene, observations, names, values, max_parameters)


def identifiability_report(
    scene: Scene,
    observations: Observations,
    names,
    values: dict,
    max_parameters: int = 64,
    normal=None,
    nuisance: int = 0,
    noise_variance: float | None = None,
    objective: str | None = None,
    segment: int | None = None,
):
    """Gauss-Newton standard errors and correlations of `values` for the full-horizon fit.

    With residuals r (observed minus simulated positions) and J = dr/d(log p), the
    covariance of log p is s^2 (J^T J)^-1 with s^2 = |r|^2 / (n - P); a parameter's
    standard error is its value times its log standard error. Warns when the data do
    not depend on a parameter, when it is poorly determined (relative standard error
    above 50%), when two parameters are confounded (|correlation| > 0.95), and when the
    loss one standard error away disagrees with the quadratic model (a rough loss).
    `normal` replaces J^T J, e.g. by the parameters' block of a fit that also estimated
    `nuisance` other values (start states, eliminated: `start_polish`), so the standard
    errors include what those unknowns leave undetermined. A fit that minimised another
    objective (multiple shooting's segments) passes its own `normal`, `noise_variance` and
    `objective` (words for the report); the whole horizon is then not simulated, and a
    parameter is "not identifiable" when its diagonal of `normal` vanishes. A fit whose final
    stage ran over segments of `segment` frames from recorded states passes `segment`: the
    residuals are those segments', and the noise of the recorded start positions they begin
    from counts in the standard errors too (`_start_sensitivity`): a fit from noisy
    starts is biased as an errors-in-variables fit is, and says so by wider errors.
    `js.identifiability` is this report for the whole horizon, without the keywords a
    fit's own stages pass.
    """
    names = tuple(names)
    flat, unravel, residuals = residual_function(scene, observations, names, values, segment)
    residuals = jax.jit(residuals)  # compiled once: here and for the roughness check
    theta = unravel(flat)
    if flat.shape[0] > max_parameters:
        return None
    dims = flat.shape[0]
    whole = noise_variance is None or normal is None
    if whole:  # the whole horizon's residuals
        r = np.asarray(residuals(flat))
        jac = np.asarray(jax.jit(jax.jacfwd(residuals))(flat))
        count = getattr(observations, "residual_count", r.shape[0])  # unseen markers carry no data
        sigma2 = float(r @ r) / max(count - dims - nuisance, 1) if noise_variance is None else float(noise_variance)
        normal = jac.T @ jac if normal is None else np.asarray(normal)
        column = np.linalg.norm(jac, axis=0)
    else:  # another objective's normal matrix and noise: the whole horizon is not simulated
        sigma2, normal = float(noise_variance), np.asarray(normal)
        column = np.sqrt(np.maximum(np.diag(normal), 0.0))
    labels = _labels(theta)
    warnings = []
    finite = bool(np.isfinite(normal).all() and np.isfinite(column).all() and np.isfinite(sigma2))
    if not finite:  # e.g. the fit ended where the time step only just simulates: the derivatives overflow
        warnings.append(
            "the derivatives of the simulation are not finite at the fitted values: no standard errors "
            "(try a smaller dt, or other initial values)"
        )
        normal, column, whole = np.zeros_like(normal), np.zeros_like(column), False
    dead = column <= 1e-10 * max(float(column.max()), 1e-300)
    for i in np.nonzero(dead)[0] if finite else ():
        warnings.append(f"{labels[i]} is not identifiable: the observed motion does not depend on it")
    # invert on unit-norm columns (so a parameter with a tiny effect is not cut off by a
    # round-off threshold), then undo the scaling; directions the data cannot see get
    # infinite variance rather than zero
    scale = np.where(dead, 1.0, np.sqrt(np.maximum(np.diag(normal), 1e-300)))
    eigenvalues, eigenvectors = np.linalg.eigh(normal / np.outer(scale, scale))
    visible = eigenvalues > 1e-13 * max(float(eigenvalues.max()), 1e-300)
    inverse = (eigenvectors[:, visible] / eigenvalues[visible]) @ eigenvectors[:, visible].T
    covariance = sigma2 * inverse / np.outer(scale, scale)
    if segment and whole and isinstance(observations, Observations):  # starts from recorded, noisy states
        moved = _start_sensitivity(scene, observations, names, theta, segment, jac)
        moved = (inverse / np.outer(scale, scale)) @ moved  # (J^T J)^-1 J^T J_x
        noise2 = observations.noise_std**2 if observations.noise_std > 0 else sigma2
        covariance = covariance + noise2 * moved @ moved.T
    log_se = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    blind = np.abs(eigenvectors[:, ~visible]).max(axis=1) > 1e-3 if (~visible).any() else np.zeros(dims, bool)
    log_se[dead | blind] = np.inf
    for i in np.nonzero((dead | blind) & (dims > 1))[0]:  # e.g. a damping run to zero, where no data reach it
        warnings.append(
            f"the other standard errors hold {labels[i]} fixed at {float(np.exp(flat[i])):.3g}: "
            "they leave out its uncertainty"
        )
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.outer(log_se, log_se)
    correlation[~np.isfinite(correlation)] = 0.0
    np.fill_diagonal(correlation, 1.0)
    se_tree = unravel(jnp.asarray(log_se))
    standard_error = {n: np.asarray(values[n]) * np.asarray(se_tree[n]) for n in names}
    relative = {n: np.asarray(se_tree[n]) for n in names}  # d(log p) = dp / p
    for i, label in enumerate(labels):
        if not dead[i] and log_se[i] > 0.5:
            warnings.append(f"{label} is poorly determined: standard error {100 * log_se[i]:.0f}% of its value")
    if whole:  # residuals simulated here (the whole horizon, or its segments): check the quadratic model
        warnings += _roughness_warnings(residuals, flat, r, jac, log_se, labels)
    for i in range(dims):
        for j in range(i + 1, dims):
            if abs(correlation[i, j]) > 0.95 and not (dead[i] or dead[j]):
                warnings.append(
                    f"{labels[i]} and {labels[j]} are confounded (correlation {correlation[i, j]:+.3f}): "
                    "the data constrain a combination of them, not each"
                )
    report = Identifiability(standard_error, relative, correlation, tuple(labels), math.sqrt(sigma2), tuple(warnings))
    return report if objective is None else dataclasses.replace(report, objective=objective)


def _start_sensitivity(scene, observations, names, theta, segment, jac):
    """J^T J_x, (P, starts' free coordinates): how the segments' recorded start positions move
    the normal equations' right-hand side, one reverse pass per parameter. Errors in variables
    to first order: a change dx of the starts moves the least-squares answer by
    -(J^T J)^-1 J^T J_x dx, so noise of variance s_x^2 on them adds
    s_x^2 (J^T J)^-1 (J^T J_x) (J^T J_x)^T (J^T J)^-1 to the covariance; s_x is the target's
    noise where known, else the residuals' standard deviation (an upper bound: they carry the
    starts' noise too). Recorded velocities and pinned particles count as exact."""
    misfit = segment_misfit_function(scene, observations, names, segment)
    data = target_data(observations)

    def of_starts(states_x):
        return misfit(theta, {**data, "states_x": states_x}).reshape(-1)

    _, pullback = jax.vjp(of_starts, data["states_x"])
    dtype = data["states_x"].dtype
    free = ~np.asarray(scene.model.pinned)  # pinned particles' positions are known
    return np.stack([np.asarray(pullback(jnp.asarray(column, dtype))[0])[:, free].reshape(-1) for column in jac.T])


def _roughness_warnings(residuals, flat, r, jac, log_se, labels) -> list[str]:
    """Check the Gauss-Newton quadratic model one standard error either side of the point.

    Moving log p_i by d = +-s_i changes the sum of squares, to second order, by
    2 (J^T r)_i d + (d |J_i|)^2. When the actual change misses that by more than half the
    curvature term, the loss is not smooth there (contact switching on at discrete steps
    does this): the standard errors are then not to be trusted and the fit may sit in a
    local dip.
    """
    warnings = []
    cost = float(r @ r)
    slope = jac.T @ r
    for i, label in enumerate(labels):
        if not (1e-6 < log_se[i] < 1.0):  # determined to round-off, or already flagged as poorly determined
            continue
        curvature = float((log_se[i] * np.linalg.norm(jac[:, i])) ** 2)
        for sign in (1.0, -1.0):
            step = sign * log_se[i]
            moved = np.array(flat, dtype=float)
            moved[i] += step
            change = float(np.sum(np.asarray(residuals(jnp.asarray(moved))) ** 2)) - cost
            predicted = 2.0 * float(slope[i]) * step + curvature
            if abs(change - predicted) > 0.5 * curvature:
                warnings.append(
                    f"{label}: the loss is not smooth near the fit (one standard error away it changes by "
                    f"{change / curvature:.2g} where the quadratic model predicts {predicted / curvature:.2g}, "
                    "in units of the curvature term); its standard error is unreliable and a gradient fit may stop in a local dip"
                )
                break
    return warnings


def _labels(theta: dict) -> list[str]:
    labels = []
    for name, value in sorted(theta.items()):
        size = int(np.size(value))
        labels += [name] if np.ndim(value) == 0 else [f"{name}[{i}]" for i in range(size)]
    return labels
