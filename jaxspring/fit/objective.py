"""What a fit minimises: the misfit of simulated to observed positions, per stage."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..errors import InputError
from ..sim.params import split_name
from ..sim.rollout import rollout
from ..sim.scene import Scene
from ..sim.state import State
from . import recording_loss
from .observations import Observations
from .recordings import RecordingTarget
from .settings import FITTABLE, Stage


def check_names(scene: Scene, names, init: dict | None):
    names = tuple(names)
    if not names:
        raise InputError("params", "nothing to fit", "name at least one parameter, e.g. ks")
    present = scene.model.parameter_values(scene.params)
    for name in names:
        if split_name(name)[0] not in FITTABLE:
            raise InputError("params", f"{name!r} cannot be fitted", f"fit some of {', '.join(FITTABLE)}")
        if name not in present:
            raise InputError(
                "params",
                f"the scene has no parameter {name!r} (its terms are {', '.join(scene.model.terms)})",
                f"fit some of {', '.join(n for n in present if split_name(n)[0] in FITTABLE)}",
            )
    for name, value in (init or {}).items():
        if name not in names:
            raise InputError(
                "init", f"{name!r} is given a start value but is not fitted", "add it to the fitted params"
            )
        try:
            value = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"init.{name}", f"{value!r:.60} is not a number", "give a positive start value") from None
        if not np.all(np.isfinite(value)) or np.any(value <= 0):
            raise InputError(
                f"init.{name}", f"must be > 0 (fitted in log space), got {value}", "give a positive start value"
            )
    return names


def misfit_function(scene: Scene, observations: Observations, names, frames: int):
    """misfit(theta, data): simulated minus observed positions over the first `frames` frames, (frames, M, 3).

    theta maps name -> log value; data holds the target and its initial state.
    """
    if isinstance(observations, RecordingTarget):
        return recording_loss.misfit_function(scene, observations, names, frames)
    model, base = scene.model, scene.params
    particles = jnp.asarray(observations.particles)
    every = observations.save_every

    def misfit(theta, data):
        params = model.params_with(base, {n: jnp.exp(theta[n]) for n in names})
        start = State(x=data["x0"], v=data["v0"])
        x = rollout(model, params, start, steps=frames * every, save_every=every).x
        return x[1:, particles] - data["x"][1 : frames + 1]

    return misfit


def segment_misfit_function(scene: Scene, observations: Observations, names, segment: int):
    """misfit(theta, data): the target cut into segments of `segment` frames, each simulated
    from the recorded state at its first frame, minus the observed positions, (count, segment, M, 3).

    The trailing frames that do not fill a segment are left out. Needs recorded states
    (`observations.full`).

    Example:
        >>> misfit = segment_misfit_function(scene, obs, ["ks"], 50)
        >>> misfit({"ks": jnp.log(250.0)}, target_data(obs)).shape  # (5, 50, M, 3) for 250 frames
    """
    model, base = scene.model, scene.params
    particles = jnp.asarray(observations.particles)
    every = observations.save_every

    def misfit(theta, data):
        params = model.params_with(base, {n: jnp.exp(theta[n]) for n in names})
        count = (data["x"].shape[0] - 1) // segment
        starts = State(
            x=data["states_x"][0 : count * segment : segment], v=data["states_v"][0 : count * segment : segment]
        )
        target = data["x"][1 : count * segment + 1].reshape((count, segment) + data["x"].shape[1:])
        run = lambda s: rollout(model, params, s, steps=segment * every, save_every=every).x[1:, particles]  # noqa: E731
        return jax.vmap(run)(starts) - target

    return misfit


def loss_function(scene: Scene, observations: Observations, names, stage: Stage):
    """loss(theta, data) for one stage; theta maps name -> log value, data holds the target."""
    if isinstance(observations, RecordingTarget):
        return recording_loss.loss_function(scene, observations, names, stage)
    if stage.kind == "shooting":
        misfit = segment_misfit_function(scene, observations, names, stage.frames)
    else:
        misfit = misfit_function(scene, observations, names, stage.frames)
    return lambda theta, data: jnp.mean(misfit(theta, data) ** 2)


def stage_residual_function(scene: Scene, observations: Observations, names, stage: Stage):
    """residual(theta, data) -> (n,) of a "direct" stage, scaled so that its sum of squares is
    the stage's loss (`loss_function`), on the pure-JAX twin of the model (Levenberg-Marquardt
    takes its Jacobian with jacfwd); None where the loss is not such a sum (another stage kind,
    a robust loss, fitted start states)."""
    if stage.kind != "direct":
        return None
    forward = dataclasses.replace(scene, model=scene.model.forward_mode())
    if isinstance(observations, RecordingTarget):
        if observations.loss != "mse" or observations.fit_start or observations.fit_driven:
            return None
        misfit = recording_loss.misfit_function(forward, observations, names, stage.frames)
        first = recording_loss.first_frame(observations)

        def residual(theta, data):  # mse over seen coordinates: zero where unseen
            count = jnp.maximum(3.0 * jnp.sum(data["seen"][:, first : stage.frames + 1]), 1.0)
            return misfit(theta, data).reshape(-1) / jnp.sqrt(count)

        return residual
    misfit = misfit_function(forward, observations, names, stage.frames)

    def residual(theta, data):  # mse over every coordinate
        r = misfit(theta, data).reshape(-1)
        return r / jnp.sqrt(r.size)

    return residual


def target_data(observations: Observations) -> dict:
    if isinstance(observations, RecordingTarget):
        return recording_loss.target_data(observations)
    data = {"x": jnp.asarray(observations.x), "x0": observations.initial_state.x, "v0": observations.initial_state.v}
    if observations.states is not None:
        data["states_x"] = jnp.asarray(observations.states.x)
        data["states_v"] = jnp.asarray(observations.states.v)
    return data


def residual_function(scene: Scene, observations: Observations, names, values: dict, segment: int | None = None):
    """(flat log parameters, unravel, residuals(flat) -> (n,)) for the full horizon, or with
    `segment` for the target cut into segments of that many frames from recorded states."""
    if isinstance(observations, RecordingTarget):
        return recording_loss.residual_function(scene, observations, names, values)
    theta = {n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names}
    flat, unravel = ravel_pytree(theta)
    forward = dataclasses.replace(scene, model=scene.model.forward_mode())  # Jacobians are taken with jacfwd
    if segment:
        if observations.states is None:
            raise InputError("segment", "segments start from recorded states, and none were recorded", "omit segment")
        misfit = segment_misfit_function(forward, observations, names, segment)
    else:
        misfit = misfit_function(forward, observations, names, observations.frame_count - 1)
    data = target_data(observations)
    return flat, unravel, lambda vector: misfit(unravel(vector), data).reshape(-1)
