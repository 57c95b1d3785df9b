"""Rollouts: one jit-compiled `lax.scan` over time steps."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._errors import InputError
from ._model import Model
from ._params import Params
from ._state import State, Trajectory


def rollout(model: Model, params: Params, state: State, steps: int, save_every: int = 1) -> Trajectory:
    """Simulate `steps` time steps and keep every `save_every`-th state.

    Pure and differentiable: works under `jax.jit` (with `steps`, `save_every`
    static), `jax.vmap` over params and/or state, and `jax.grad` with respect
    to params and state.

    Args:
        model: static structure (topology, force terms, integrator, dt).
        params: physical parameters (see `Params`).
        state: initial state, x and v of shape (N, 3).
        steps: number of time steps; a multiple of `save_every`.
        save_every: keep one frame every this many steps.
    Returns:
        Trajectory with x, v of shape (steps // save_every + 1, N, 3) and t of
        shape (frames,); frame 0 is the initial state.

    Example:
        >>> scene = js.load_scene("cloth")
        >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=2000, save_every=10)
    """
    frames = _frame_count(steps, save_every)
    _, x, v = _simulate(model, params, state, frames, save_every)
    t = jnp.arange(frames + 1) * (save_every * model.dt)
    return Trajectory(
        x=jnp.concatenate([state.x[None], x], axis=0),
        v=jnp.concatenate([state.v[None], v], axis=0),
        t=t.astype(state.x.dtype),
    )


def final_state(model: Model, params: Params, state: State, steps: int) -> State:
    """The state after `steps` time steps, without storing frames.

    Example:
        >>> end = js.final_state(scene.model, scene.params, scene.state, steps=1000)
    """
    end, _, _ = _simulate(model, params, state, 1, int(steps))
    return end


def _frame_count(steps, save_every) -> int:
    steps, save_every = int(steps), int(save_every)
    if save_every < 1:
        raise InputError("save_every", f"must be >= 1, got {save_every}", "save at least every step")
    if steps < 0 or steps % save_every:
        raise InputError(
            "steps",
            f"{steps} is not a non-negative multiple of save_every={save_every}",
            "choose steps divisible by save_every",
        )
    return steps // save_every


@functools.partial(jax.jit, static_argnames=("frames", "save_every"))
def _simulate(model, params, state, frames, save_every):
    def one_step(current, _):
        return model.step(params, current), None

    def one_frame(current, _):
        current, _ = jax.lax.scan(one_step, current, None, length=save_every)
        return current, (current.x, current.v)

    end, (x, v) = jax.lax.scan(one_frame, state, None, length=frames)
    return end, x, v


def energy(model: Model, params: Params, state: State) -> jax.Array:
    """Total mechanical energy [J] of a state, or of every frame of a Trajectory.

    Example:
        >>> e = js.energy(scene.model, scene.params, traj)   # shape (frames,)
    """
    if isinstance(state, Trajectory):
        return jax.vmap(lambda x, v: model.energy(params, State(x=x, v=v)))(state.x, state.v)
    return model.energy(params, state)
