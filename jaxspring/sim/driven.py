"""Driven particles: particles moved from outside along given paths (hands, robots, clamps).

A `Drive` names the driven particles and their positions at knot times (a recording's
frames); between knots the path is linear, so its velocity is the secant between the
two knots around a time. Every step of a driven rollout

1. puts each driven particle at its path's position at the step's start time t and gives
   it the velocity (p(t + dt) - p(t)) / dt, the path's velocity over the step;
2. runs the model's integrator with the driven particles not free: they keep that
   velocity through the step, so every force evaluation sees them on the straight line
   from p(t) to p(t + dt) (RK4's stages at their stage times, backward Euler's implicit
   force at p(t + dt): prescribed values, not unknowns);
3. puts them at p(t + dt) exactly.

The same code runs every integrator, under jit, vmap (over parameters, states and
drives) and grad. It needs a stepper in particle layout that steps one step at a time:
the generic and native-springs steppers; a lattice model on a fused native stepper runs
its drives on the generic pure-JAX stepper (announced once when backend "native" was
asked for).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..steppers.base import Generic
from .checks import particle_indices
from .state import State, Trajectory


@functools.partial(jax.tree_util.register_dataclass, data_fields=["t", "x", "v"], meta_fields=["particles"])
@dataclasses.dataclass(frozen=True)
class Drive:
    """Driven particles and their paths.

    Attributes:
        particles: indices of the driven particles, a tuple of D ints (static under jit).
        t: knot times [s], shape (K,), strictly increasing, K >= 2.
        x: positions at the knots [m], shape (K, D, 3); linear in between, held
            constant outside [t[0], t[-1]].
        v: optional velocities at the knots [m/s], (K, D, 3): the path is then the cubic
            Hermite curve through positions and velocities (smooth, no kink at the knots).

    Example:
        >>> drive = js.sim.Drive(particles=(0,), t=[0.0, 1.0], x=[[[0.0, 0.0, 0.0]], [[0.1, 0.0, 0.0]]])
        >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=1000, drive=drive)
    """

    particles: tuple
    t: jax.Array
    x: jax.Array
    v: jax.Array | None = None

    def at(self, time) -> jax.Array:
        """Positions (D, 3) of the driven particles at `time` (a scalar)."""
        last = self.t.shape[-1] - 2
        k = jnp.clip(jnp.searchsorted(self.t, time, side="right") - 1, 0, last)
        h = self.t[k + 1] - self.t[k]
        w = jnp.clip((time - self.t[k]) / h, 0.0, 1.0)
        if self.v is None:
            return (1.0 - w) * self.x[k] + w * self.x[k + 1]
        w2, w3 = w * w, w * w * w
        return (
            (2 * w3 - 3 * w2 + 1) * self.x[k]
            + (w3 - 2 * w2 + w) * h * self.v[k]
            + (3 * w2 - 2 * w3) * self.x[k + 1]
            + (w3 - w2) * h * self.v[k + 1]
        )


def make_drive(particles, t, x, particle_count: int, pinned=None) -> Drive:
    """A checked `Drive` (the one-line errors users see); arrays as float64 NumPy.

    Example:
        >>> drive = make_drive([0, 19], t, x, scene.model.particle_count, scene.model.pinned)
    """
    indices = particle_indices("driven", particles, particle_count, "give indices of the scene's particles")
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    if indices.size == 0:
        raise InputError("driven", "names no particle", "list the driven particles, e.g. driven = [0]")
    if np.unique(indices).size != indices.size:
        raise InputError("driven", "names a particle twice", "list each driven particle once")
    if pinned is not None and np.asarray(pinned)[indices].any():
        bad = int(indices[np.asarray(pinned)[indices]][0])
        raise InputError("driven", f"particle {bad} is pinned", "a particle is either pinned or driven: unpin it")
    if t.ndim != 1 or t.shape[0] < 2 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise InputError("drive.t", "must be >= 2 finite, strictly increasing times", "fix the knot times")
    if x.shape != (t.shape[0], indices.size, 3):
        raise InputError(
            "drive.x", f"has shape {x.shape}, expected {(t.shape[0], indices.size, 3)}", "give (knots, driven, 3)"
        )
    if not np.all(np.isfinite(x)):
        raise InputError("drive.x", "contains NaN or infinite positions", "fill the gaps in the driven paths")
    return Drive(particles=tuple(int(i) for i in indices), t=t, x=x)


_ANNOUNCED: set = set()


def particle_stepper(model):
    """The stepper a driven rollout of `model` uses (the model's own where it can)."""
    stepper = model.stepper
    if stepper.layout == "particles" and not stepper.fused:
        return stepper
    if model.backend == "native" and stepper.name not in _ANNOUNCED:
        _ANNOUNCED.add(stepper.name)
        warnings.warn(
            f"jaxspring: the {stepper.name} stepper does not run driven particles; "
            "driven rollouts of this model run on the generic pure-JAX stepper",
            stacklevel=3,
        )
    return Generic()


def driven_simulate(model, params, state: State, drive: Drive, t0, frames: int, save_every: int, observed=None):
    """(end state, x, v) with x, v (frames, M, 3) of the `observed` particles (default all)
    every `save_every` steps of a driven rollout from `state` at time `t0`.

    `frames` and `save_every` are static. With `save_every` > 1 each frame's steps are
    rematerialised in the backward pass, so reverse-mode memory grows with the frames,
    not the steps.
    """
    stepper = particle_stepper(model)
    count, dt = state.x.shape[0], model.dt
    index = jnp.asarray(drive.particles, dtype=jnp.int32)
    driven = jnp.zeros((count, 1), bool).at[index].set(True)
    observed = slice(None) if observed is None else jnp.asarray(observed)
    t0 = jnp.asarray(t0, state.x.dtype)

    def step(current, n):
        time = t0 + n * dt
        here, there = drive.at(time), drive.at(time + dt)
        current = State(x=current.x.at[index].set(here), v=current.v.at[index].set((there - here) / dt))
        current = stepper.step(model, params, current, driven=driven)
        return current.replace(x=current.x.at[index].set(there)), None

    def frame(current, k):
        steps = k * save_every + jnp.arange(save_every)
        current = jax.lax.scan(step, current, steps)[0]
        return current, (current.x[observed], current.v[observed])

    if save_every > 1:
        frame = jax.checkpoint(frame)
    return jax.lax.scan(frame, state, jnp.arange(frames))


@functools.partial(jax.jit, static_argnames=("frames", "save_every"))
def driven_rollout(model, params, state: State, drive: Drive, frames: int, save_every: int, t0) -> Trajectory:
    """The Trajectory of a driven rollout (see `rollout`'s `drive`)."""
    _, (x, v) = driven_simulate(model, params, state, drive, t0, frames, save_every)
    t = jnp.asarray(t0, state.x.dtype) + jnp.arange(frames + 1) * (save_every * model.dt)
    return Trajectory(
        x=jnp.concatenate([state.x[None], x]), v=jnp.concatenate([state.v[None], v]), t=t.astype(state.x.dtype)
    )


def steps_to_reach(duration: float, dt: float) -> int:
    """Time steps of `dt` that cover `duration` (the last step may pass its end by < dt)."""
    return max(1, math.ceil(duration / dt - 1e-9))
