"""Rollouts: one jit-compiled `lax.scan` over time steps."""

from __future__ import annotations

import functools
import math
import operator

import jax
import jax.numpy as jnp

from ..errors import InputError
from .checks import check_params
from .driven import Drive, driven_rollout
from .model import Model
from .params import Params
from .state import State, Trajectory


def rollout(
    model: Model,
    params: Params,
    state: State,
    steps: int,
    save_every: int = 1,
    checkpoint=None,
    drive: Drive | None = None,
    t0=0.0,
) -> Trajectory:
    """Simulate `steps` time steps and keep every `save_every`-th state.

    Pure and differentiable: works under `jax.jit` (with `steps`, `save_every`,
    `checkpoint` static), `jax.vmap` over params and/or state, and `jax.grad` with
    respect to params and state.

    Args:
        model: static structure (topology, force terms, integrator, dt).
        params: physical parameters (see `Params`).
        state: initial state, x and v of shape (N, 3).
        steps: number of time steps (an int, 0 to `MAX_STEPS`); a multiple of `save_every`; 0 gives
            frame 0 only.
        save_every: keep one frame every this many steps.
        checkpoint: reverse-mode memory against time. None (default): keep every
            step's intermediate values, the fastest gradient, memory ~ steps. "sqrt":
            keep only the state every ~sqrt(steps) steps and recompute in between,
            memory ~ sqrt(steps) states, about one more forward pass. An int K: the
            same with segments of K steps. The forward values are identical.
        drive: particles moved along given paths (a `Drive`, see `sim.driven`); they are
            placed on their paths at every step, whatever `state` holds for them.
        t0: the time [s] of `state` on the drive's clock (frame k is at t0 + k * save_every * dt).
    Returns:
        Trajectory with x, v of shape (steps // save_every + 1, N, 3) and t of
        shape (frames,); frame 0 is the initial state.

    Example:
        >>> scene = js.load_scene("cloth")
        >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=2000, save_every=10)
    """
    frames = frame_count(steps, save_every)
    state = _in_model_precision(model, state)
    _check_known_params(model, params)
    if frames == 0:  # frame 0 only
        return Trajectory(x=state.x[None], v=state.v[None], t=jnp.full(1, t0, state.x.dtype))
    if drive is not None:
        return driven_rollout(model, params, state, drive, frames, save_every, t0)
    segment = _segment_length(checkpoint, frames * save_every)
    if segment is None:
        _, x, v = simulate(model, params, state, frames, save_every)
    else:
        _, x, v = _simulate_checkpointed(model, params, state, frames, save_every, segment)
    t = t0 + jnp.arange(frames + 1) * (save_every * model.dt)
    return Trajectory(
        x=jnp.concatenate([state.x[None], x], axis=0),
        v=jnp.concatenate([state.v[None], v], axis=0),
        t=t.astype(state.x.dtype),
    )


def final_state(model: Model, params: Params, state: State, steps: int) -> State:
    """The state after `steps` time steps, without storing frames.

    Example:
        >>> end = js.sim.final_state(scene.model, scene.params, scene.state, steps=1000)
    """
    steps = step_count(steps, "steps", minimum=0)
    state = _in_model_precision(model, state)
    _check_known_params(model, params)
    if steps == 0:
        return state
    end, _, _ = simulate(model, params, state, 1, steps)
    return end


def _check_known_params(model: Model, params: Params) -> None:
    """`check_params` on params whose values are known here (not traced under jit, vmap or
    grad): a negative, NaN or misshapen value, or one for a term the scene lacks, is a
    one-line InputError, not a NaN trajectory or a broadcasting error."""
    if not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(params)):
        check_params(model, params)


def _in_model_precision(model: Model, state: State) -> State:
    """The state promoted to the wider of its own and the model's precisions, which the step
    computes in (a float32 state read from a file meets a float64 model when x64 is on); a
    state already there is returned as is."""
    expected = (model.particle_count, 3)
    for field in ("x", "v"):
        shape = jnp.shape(getattr(state, field))
        if shape != expected:
            raise InputError(
                f"state.{field}", f"has shape {shape} but the model has {expected[0]} particles", f"give {expected}"
            )
    dtype = jnp.result_type(state.x, state.v, model.mass)
    if state.x.dtype == dtype and state.v.dtype == dtype:
        return state
    return State(x=jnp.asarray(state.x, dtype), v=jnp.asarray(state.v, dtype))


MAX_STEPS = 10**9
"""The most time steps one call takes: far beyond any scene, and it stops a typo or an
overflowing count (2**32) before the scan is built."""


def step_count(value, field: str, minimum: int) -> int:
    """`value` as an int in [minimum, MAX_STEPS]; floats, strings and bools raise `InputError`.

    Example:
        >>> step_count(100, "steps", minimum=0)
        100
    """
    try:
        if isinstance(value, bool):
            raise TypeError
        count = operator.index(value)
    except TypeError:
        raise InputError(
            field, f"must be an integer, got {value!r}", f"give a whole number such as {field}=100"
        ) from None
    if count < minimum:
        raise InputError(field, f"must be >= {minimum}, got {count}", f"give {field} >= {minimum}")
    if count > MAX_STEPS:
        raise InputError(field, f"must be at most {MAX_STEPS:,}, got {count:,}", "split the run into shorter ones")
    return count


def frame_count(steps, save_every, fields=("steps", "save_every")) -> int:
    """Frames after frame 0 of a rollout of `steps` steps saving every `save_every`-th; both checked.

    `fields` names the two values in an error (e.g. the CLI's "--steps", "--save-every").

    Example:
        >>> frame_count(1000, 10)
        100
    """
    steps, save_every = step_count(steps, fields[0], minimum=0), step_count(save_every, fields[1], minimum=1)
    if steps % save_every:
        raise InputError(
            fields[0],
            f"{steps} is not a multiple of {fields[1]}={save_every}",
            f"choose {fields[0]} divisible by {fields[1]}",
        )
    return steps // save_every


@functools.partial(jax.jit, static_argnames=("frames", "save_every"))
def simulate(model, params, state, frames, save_every):
    """(end state, x, v (frames, N, 3)); the scan runs in the model's internal layout."""

    stepper = model.stepper

    def one_frame(current, _):
        current = stepper.advance(model, params, current, save_every)
        return current, (current.x, current.v)

    end, (x, v) = jax.lax.scan(one_frame, stepper.to_internal(model, state), None, length=frames)
    return _outside(model, end, x, v)


def _outside(model, end, x, v):
    """End state and frames from the stepper's layout back to (N, 3)."""
    stepper = model.stepper
    return (
        stepper.from_internal(model, end),
        stepper.array_from_internal(model, x),
        stepper.array_from_internal(model, v),
    )


def _segment_length(checkpoint, steps: int):
    if checkpoint is None:
        return None
    if checkpoint == "sqrt":
        return max(1, math.isqrt(max(steps, 1)))
    if isinstance(checkpoint, bool) or not isinstance(checkpoint, int) or checkpoint < 1:
        raise InputError("checkpoint", f"must be None, 'sqrt' or a positive int, got {checkpoint!r}", "use 'sqrt'")
    return int(checkpoint)


@functools.partial(jax.jit, static_argnames=("frames", "save_every", "segment"))
def _simulate_checkpointed(model, params, state, frames, save_every, segment):
    """`simulate` storing only segment-boundary states for reverse mode.

    Every step is rematerialised (its residuals are recomputed from its input state
    during the backward pass), and so is every segment of `segment` steps: the
    backward pass keeps one state per segment plus one per step of the segment
    being differentiated.
    """
    stepper = model.stepper
    step = jax.checkpoint(lambda current: stepper.step(model, params, current))

    def run(current, length):
        if stepper.fused:  # one call; its reverse pass keeps its own checkpoints
            return stepper.advance(model, params, current, length)
        return jax.lax.scan(lambda c, _: (step(c), None), current, None, length=length)[0]

    if save_every >= segment:
        chunks, rest = divmod(save_every, segment)
        chunk = jax.checkpoint(lambda current: run(current, segment))

        def one_frame(current, _):
            current = jax.lax.scan(lambda c, _: (chunk(c), None), current, None, length=chunks)[0]
            if rest:
                current = jax.checkpoint(lambda c: run(c, rest))(current)
            return current, (current.x, current.v)

        end, (x, v) = jax.lax.scan(one_frame, stepper.to_internal(model, state), None, length=frames)
        return _outside(model, end, x, v)

    per_block = max(1, segment // save_every)
    blocks, rest = divmod(frames, per_block)

    def frame(current, _):
        current = run(current, save_every)
        return current, (current.x, current.v)

    def block(current, count):
        return jax.lax.scan(frame, current, None, length=count)

    checkpointed = jax.checkpoint(lambda c: block(c, per_block))
    end, (x, v) = jax.lax.scan(lambda c, _: checkpointed(c), stepper.to_internal(model, state), None, length=blocks)
    x, v = x.reshape((-1,) + x.shape[2:]), v.reshape((-1,) + v.shape[2:])
    if rest:
        end, (xr, vr) = jax.checkpoint(lambda c: block(c, rest))(end)
        x, v = jnp.concatenate([x, xr]), jnp.concatenate([v, vr])
    return _outside(model, end, x, v)


def energy(model: Model, params: Params, state: State) -> jax.Array:
    """Total mechanical energy [J] of a state, or of every frame of a Trajectory.

    Example:
        >>> e = js.sim.energy(scene.model, scene.params, traj)   # shape (frames,)
    """
    if isinstance(state, Trajectory):
        return _frame_energies(model, params, state.x, state.v)
    return _state_energy(model, params, state.x, state.v)


@jax.jit
def _frame_energies(model, params, x, v):
    # one compiled program (not an eager dispatch per operation: each compiles apart, ~40 ms)
    return jax.vmap(lambda x, v: model.energy(params, State(x=x, v=v)))(x, v)


@jax.jit
def _state_energy(model, params, x, v):
    return model.energy(params, State(x=x, v=v))


@jax.jit
def term_energies(model: Model, params: Params, x: jax.Array) -> tuple:
    """Each force term's potential energy at positions x [J], in `model.force_terms` order."""
    return tuple(term.energy(model, params, x) for term in model.force_terms)
