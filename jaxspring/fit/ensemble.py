"""The ensemble stage as an (init, update) pair: Gauss-Newton on a loss smoothed over a cloud."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..sim.scene import Scene
from .objective import misfit_function
from .observations import Observations
from .settings import Stage


def ensemble_step_function(scene: Scene, observations: Observations, names, stage: Stage, settings, batched, theta):
    """(step, init) of an ensemble stage, with the signatures of `step.step_function`'s.

    Gauss-Newton on the loss smoothed over a cloud of log-parameter values u + A z (z a
    fixed symmetric set of standard normal points, A the spread). A step rolls out the
    candidate centre and its cloud in one batch; a linear fit of the cloud's residuals
    gives the smoothed residual c and Jacobian J, hence the next step
    -(J^T J + lambda diag)^-1 J^T c (Levenberg-Marquardt: a step is taken when the
    smoothed loss falls). When the steps become small against the spread (or stop
    being accepted), the spread is halved, in the shape of the parameters' standard
    errors s (J^T J)^-1/2, and the search goes on; the stage ends once the spread is
    the standard errors (or, for data explained to rounding, the square root of the dtype's
    epsilon). The first cloud is at most 3 standard errors wide (measured by
    the first evaluation, at the stage's start spread), so a start that already explains
    the data is not smoothed away from. Every step returns the plain loss at
    the centre, so the history shows the loss the stage minimises in the end.
    """
    members = settings.ensemble_members
    flat, unravel = ravel_pytree({n: theta[n][0] for n in names})
    size, dtype = flat.shape[0], flat.dtype
    half = np.random.default_rng(0).standard_normal((members // 2, size))
    cloud_points = jnp.asarray(np.concatenate([half, -half]), dtype=dtype)
    tiny = float(jnp.finfo(dtype).tiny)
    # The narrowest cloud whose residual differences rise above rounding: the square root of
    # the dtype's epsilon, as for a finite difference. Standard errors below it (data
    # explained to rounding) are not resolved: the stage ends at it.
    floor = float(np.sqrt(jnp.finfo(dtype).eps))
    start_spread = settings.ensemble_spread if stage.spread is None else stage.spread

    def no_narrower_than_floor(spread):  # along every axis: a narrower one measures round-off
        left, sizes, right = jnp.linalg.svd(spread)
        return (left * jnp.maximum(sizes, floor)) @ right

    misfit = misfit_function(scene, observations, names, stage.frames)

    def residuals(vector, data, extras):  # extras: theta's other entries (a fitted start), held
        return misfit({**extras, **unravel(vector)}, data).reshape(-1)

    def init(theta_member):
        eye = jnp.eye(size, dtype=dtype)
        zero = jnp.zeros((), dtype)
        return {
            "spread": start_spread * eye,
            "damping": jnp.asarray(1e-3, dtype),
            "fresh": zero + 1,  # the next step evaluates the centre with a new spread
            "done": zero,
            "smoothed": zero + jnp.inf,
            "loss": zero + jnp.inf,
            "sigma2": zero,
            "gradient": jnp.zeros(size, dtype),
            "normal": eye,
        }

    def single(theta_member, state, data):
        centre = ravel_pytree({n: theta_member[n] for n in names})[0]
        fresh = state["fresh"] > 0
        normal = state["normal"]
        step = -jnp.linalg.solve(normal + state["damping"] * jnp.diag(jnp.diag(normal)), state["gradient"])
        step = jnp.where(fresh | ~jnp.all(jnp.isfinite(step)), 0.0, step)
        candidate = centre + step
        cloud = candidate + cloud_points @ state["spread"].T
        extras = {k: v for k, v in theta_member.items() if k not in names}
        r = jax.vmap(residuals, in_axes=(0, None, None))(jnp.concatenate([candidate[None], cloud]), data, extras)
        r_centre, r = r[0], r[1:]
        count = r_centre.shape[0]
        finite = jnp.all(jnp.isfinite(r), axis=1)
        weight = finite.astype(dtype)
        used = jnp.maximum(weight.sum(), 1.0)
        r = jnp.where(finite[:, None], r, 0.0)
        mean = weight @ r / used
        smoothed = weight @ jnp.sum(r**2, axis=1) / (used * count)
        usable = (weight.sum() >= 0.75 * members) & jnp.all(jnp.isfinite(r_centre))
        smoothed = jnp.where(usable, smoothed, jnp.inf)
        offsets = (cloud - weight @ cloud / used) * weight[:, None]
        slopes = jnp.linalg.solve(offsets.T @ offsets, offsets.T @ ((r - mean) * weight[:, None]))  # J^T, (P, n)
        accept = usable & (fresh | (smoothed < state["smoothed"]))
        chosen = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        normal = chosen(slopes @ slopes.T, normal)
        sigma2 = chosen(r_centre @ r_centre / max(count - size, 1), state["sigma2"])
        new = {
            "gradient": chosen(slopes @ mean, state["gradient"]),
            "normal": normal,
            "sigma2": sigma2,
            "smoothed": chosen(smoothed, state["smoothed"]),
            "loss": chosen(r_centre @ r_centre / count, state["loss"]),
        }
        damping = jnp.where(accept, jnp.maximum(state["damping"] / 10, 1e-6), state["damping"] * 10)
        # The standard errors' square root s (J^T J)^-1/2 and the spread's axes measured in it.
        # A level halves the spread (in the standard errors' shape) until it is the standard
        # errors; where the cloud's residuals are linear in the parameters to 1% (the loss is
        # smooth at this scale: no dips to step over) it goes straight there. The spread never
        # exceeds its start; the stage ends when it is within 10% of the standard errors or
        # cannot shrink further (a parameter the data barely determine).
        eigenvalues, vectors = jnp.linalg.eigh(normal)
        eigenvalues = jnp.maximum(eigenvalues, 1e-12 * eigenvalues.max() + tiny)
        noise = jnp.sqrt(jnp.maximum(sigma2, tiny))
        posterior = (vectors * (noise / jnp.sqrt(eigenvalues))) @ vectors.T
        whiten = (vectors * (jnp.sqrt(eigenvalues) / noise)) @ vectors.T
        sizes = jnp.linalg.svd(whiten @ state["spread"], compute_uv=False)
        # A level ends when the steps left are small against the spread, or below a tenth of
        # a standard error (a flat valley: further steps move nothing the data determine),
        # or when no step is accepted.
        relative = jnp.linalg.norm(jnp.linalg.solve(state["spread"], step))
        significant = jnp.linalg.norm(whiten @ step)
        level_end = ~fresh & ((relative <= 0.1) | (significant <= 0.1) | (~accept & (damping >= 1e3)))
        fitted = offsets @ slopes
        nonlinear = jnp.sum(((r - mean) * weight[:, None] - fitted) ** 2) / jnp.maximum(jnp.sum(fitted**2), tiny)
        shrunk = posterior * jnp.where(nonlinear < 1e-2, 1.0, jnp.maximum(1.0, sizes.min() / 2))
        shrunk = shrunk * jnp.minimum(1.0, start_spread / jnp.linalg.norm(shrunk, 2))
        shrunk = no_narrower_than_floor(shrunk)
        stalled = jnp.linalg.norm(shrunk, 2) >= 0.9 * jnp.linalg.norm(state["spread"], 2)
        finished = level_end & ((sizes.max() <= 1.1) | stalled)
        failed_start = fresh & ~usable  # the cloud reaches unstable values: halve it and evaluate again
        # The first cloud never spans more than 3 standard errors (where the truth plausibly
        # lies) around a start that already explains the data that well: a wider cloud would
        # smooth the loss over motions the data rule out, and its minimum need not be theirs
        # (a 1 s jelly at its truth to 1e-9 was walked to kd 34% off by a 10% cloud). A start
        # far off leaves a large misfit, hence large standard errors: its cloud stays as given.
        plausible = no_narrower_than_floor(3.0 * posterior)
        narrower = jnp.linalg.norm(plausible, 2) < 0.5 * jnp.linalg.norm(state["spread"], 2)
        first = fresh & usable & jnp.isinf(state["smoothed"]) & narrower
        spread = jnp.where(level_end & ~finished, shrunk, state["spread"])
        spread = jnp.where(failed_start, spread / 2, spread)
        spread = jnp.where(first, plausible, spread)
        new.update(
            spread=spread,
            damping=jnp.where(level_end, jnp.asarray(1e-3, dtype), damping),
            fresh=(level_end & ~finished) | failed_start | first,
            done=finished | (state["done"] > 0),
        )
        new = {k: jnp.asarray(v, dtype) for k, v in new.items()}
        value = jnp.where(fresh, new["loss"], state["loss"])
        moved = unravel(candidate)
        theta_new = {**theta_member}
        theta_new.update({n: jnp.where(accept & (state["done"] == 0), moved[n], theta_member[n]) for n in names})
        return theta_new, new, value

    step = jax.jit(jax.vmap(single, in_axes=(0, 0, 0 if batched else None)))
    return step, jax.jit(jax.vmap(init))
