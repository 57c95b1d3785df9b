"""The fit's functions on a `RecordingTarget`: its arrays, simulated markers at frame times,
the misfit, the loss of a stage (whole takes or shooting segments) and residuals.

With `fit_start`, every recording's start state is fitted too: corrections to the start
rule's positions and velocities of the free particles (`START_SCALE` m and m/s units),
an entry "start" of theta beside the log parameters, with the start frame's own markers
in the misfit. With `fit_driven`, every recording's driven paths too: corrections to each
driven marker's position at every frame (`DRIVEN_SCALE` m units), entry "driven" of theta,
the paths linear between the corrected positions.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..sim.driven import Drive, driven_simulate, steps_to_reach
from ..sim.state import State
from .recordings import RecordingTarget

START_SCALE = (1e-3, 1e-2)
"""Units of theta["start"]: position corrections in mm, velocity corrections in cm/s, so
that their steps are of the size of the log parameters'."""
DRIVEN_SCALE = 1e-3
"""Units of theta["driven"]: position corrections of the driven paths in mm."""
NUISANCE = ("start", "driven")
"""theta's entries besides the log parameters: unknowns of each recording (`start_unknowns`)."""


def start_unknowns(target) -> dict:
    """theta's extra entries for `target`: "start" zeros (R, N, 6) with `fit_start`, and
    "driven" zeros (R, F, D, 3) with `fit_driven`."""
    out = {}
    dtype = getattr(target, "states_x", np.zeros(0)).dtype
    if getattr(target, "fit_start", False):
        out["start"] = jnp.zeros(target.states_x[:, 0].shape[:-1] + (6,), dtype=dtype)
    if getattr(target, "fit_driven", False):
        out["driven"] = jnp.zeros(target.x.shape[:2] + (len(target.driven), 3), dtype=dtype)
    return out


def _with_driven(target, theta, filled):
    """The markers' paths `filled` (R, F, M, 6) with theta["driven"]'s corrections on the driven markers."""
    if not target.fit_driven:
        return filled
    return filled.at[..., carriers(target), :3].add(DRIVEN_SCALE * theta["driven"])


def _start(target, theta, x0, v0):
    """Start states (R, N, 3) x2: the start rule's, corrected by theta["start"] on free particles."""
    if not target.fit_start:
        return x0, v0
    correction = jnp.where(jnp.asarray(target.free)[:, None], theta["start"], 0.0)
    return x0 + START_SCALE[0] * correction[..., :3], v0 + START_SCALE[1] * correction[..., 3:]


def with_fitted_start(target, nuisance: dict):
    """`target` with a fit's `nuisance` unknowns ({"start": (R, N, 6), "driven": (R, F, D, 3)})
    folded in: its start states and driven paths are the fitted ones, held from then on."""
    if not target.fit_start or not nuisance:
        return target
    theta = {k: jnp.asarray(v) for k, v in nuisance.items()}
    x0, v0 = _start(target, theta, target.states_x[:, 0], target.states_v[:, 0])
    states_x, states_v = np.array(target.states_x), np.array(target.states_v)
    states_x[:, 0], states_v[:, 0] = np.asarray(x0), np.asarray(v0)
    filled = np.asarray(_with_driven(target, theta, jnp.asarray(target.filled)))
    states_x[:, 0, target.driven] = filled[:, 0, carriers(target), :3]
    smooth = 0 if target.fit_driven else target.smooth  # fitted paths are linear between frames
    return dataclasses.replace(
        target, states_x=states_x, states_v=states_v, filled=filled, smooth=smooth, fit_start=False, fit_driven=False
    )


def estimated_inputs(target, driven: bool) -> dict:
    """A fitted target's (`with_fitted_start`) start states and, if `driven`, driven paths, in m and m/s."""
    out = {"x0": np.asarray(target.states_x[:, 0]), "v0": np.asarray(target.states_v[:, 0])}
    if driven:
        out["driven"] = np.asarray(target.filled[:, :, carriers(target), :3])
    return out


def target_data(target: RecordingTarget) -> dict:
    seen = np.isfinite(target.x).all(axis=-1)
    return {
        "times": jnp.asarray(target.times),
        "x": jnp.asarray(np.where(seen[..., None], target.x, 0.0)),
        "seen": jnp.asarray(seen),
        "filled": jnp.asarray(target.filled),
        "states_x": jnp.asarray(target.states_x),
        "states_v": jnp.asarray(target.states_v),
    }


def carriers(target) -> np.ndarray:
    """The marker each driven particle carries, int (D,)."""
    return np.array([int(np.nonzero(target.markers == p)[0][0]) for p in target.driven], dtype=np.int64)


def _segment_steps(target, first: int, length: int) -> int:
    """Steps covering `length` frames from frame `first` in every recording."""
    last = np.minimum(first + length, target.frame_count - 1)
    return steps_to_reach(float(np.max(target.times[:, last] - target.times[:, first])), target.dt)


def markers_simulated(model, params, target: RecordingTarget, times, filled, x0, v0, steps: int, at):
    """Simulated marker positions (K, M, 3) at times `at` (K,) of one recording, from state
    (x0, v0) at `times[0]`, its driven particles along `filled`'s driven markers."""
    paths = filled[:, carriers(target)]
    velocities = paths[..., 3:] if target.smooth and not target.fit_driven else None
    x0 = x0.at[jnp.asarray(target.driven)].set(paths[0, :, :3])  # the driven particles start on their paths
    drive = Drive(particles=tuple(int(p) for p in target.driven), t=times - times[0], x=paths[..., :3], v=velocities)
    _, (x, _) = driven_simulate(model, params, State(x=x0, v=v0), drive, 0.0, steps, 1, target.markers)
    path = jnp.concatenate([x0[target.markers][None], x])  # (steps + 1, M, 3) at n dt
    s = (at - times[0]) / model.dt
    k = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, steps - 1)
    w = jnp.clip(s - k, 0.0, 1.0)[:, None, None]
    return (1.0 - w) * path[k] + w * path[k + 1]


def _recording_misfit(model, target: RecordingTarget, frames: int, first: int):
    """misfit of one recording over frames first..`frames` from its start state (x0, v0)."""
    steps = _segment_steps(target, 0, frames)

    def one(params, times, x, seen, filled, x0, v0):
        simulated = markers_simulated(model, params, target, times, filled, x0, v0, steps, times[first : frames + 1])
        return jnp.where(seen[first : frames + 1, :, None], simulated - x[first : frames + 1], 0.0)

    return one


def misfit_function(scene, target: RecordingTarget, names, frames: int):
    """misfit(theta, data): simulated minus seen marker positions over frames 1..`frames`
    (0..`frames` with a fitted start) of every recording, zero where unseen, (R, K, M, 3)."""
    model, base = scene.model, scene.params
    one = _recording_misfit(model, target, frames, first_frame(target))

    def misfit(theta, data):
        params = model.params_with(base, {n: jnp.exp(theta[n]) for n in names})
        x0, v0 = _start(target, theta, data["states_x"][:, 0], data["states_v"][:, 0])
        filled = _with_driven(target, theta, data["filled"])
        run = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0, 0))
        return run(params, data["times"], data["x"], data["seen"], filled, x0, v0)

    return misfit


def block_problem(scene, target: RecordingTarget, names, values: dict, nuisance: dict):
    """The fit with fitted start states (and driven paths) as a block least-squares problem
    (`block_lm`): shared p = log parameters, each recording's own s = its free particles'
    start corrections (`START_SCALE` units) and, with `fit_driven`, its driven paths'
    corrections (`DRIVEN_SCALE`), residuals over its whole length from the start frame.
    `nuisance`: where they start, as `start_unknowns` (missing entries: zero).

    Returns (p0, unravel, s0 (R, L), residual(p, s_b, data_b), data, to_nuisance(s) -> dict)."""
    from jax.flatten_util import ravel_pytree

    model, base = scene.model.forward_mode(), scene.params  # Jacobians are taken with jacfwd
    p0, unravel = ravel_pytree({n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names})
    free = np.nonzero(target.free)[0]
    nuisance = {k: np.asarray(nuisance.get(k, v)) for k, v in start_unknowns(target).items()}
    start, driven = nuisance["start"], nuisance.get("driven")
    local = free.size * 6
    s0 = start[:, free].reshape(start.shape[0], -1)
    if driven is not None:
        s0 = np.concatenate([s0, driven.reshape(driven.shape[0], -1)], axis=1)
    one = _recording_misfit(model, target, target.frame_count - 1, 0)
    data = target_data(target)
    data = {**data, "states_x": data["states_x"][:, 0], "states_v": data["states_v"][:, 0]}
    car = carriers(target)

    def residual(p, s_b, d):
        params = model.params_with(base, {n: jnp.exp(v) for n, v in unravel(p).items()})
        correction = s_b[:local].reshape(-1, 6)
        x0 = d["states_x"].at[free].add(START_SCALE[0] * correction[:, :3])
        v0 = d["states_v"].at[free].add(START_SCALE[1] * correction[:, 3:])
        filled = d["filled"]
        if driven is not None:
            filled = filled.at[:, car, :3].add(DRIVEN_SCALE * s_b[local:].reshape(filled.shape[0], car.size, 3))
        return one(params, d["times"], d["x"], d["seen"], filled, x0, v0).reshape(-1)

    def to_nuisance(s):
        s = np.asarray(s)
        out = {"start": np.zeros_like(start)}
        out["start"][:, free] = s[:, :local].reshape(len(s), -1, 6)
        if driven is not None:
            out["driven"] = s[:, local:].reshape(driven.shape)
        return out

    return p0, unravel, s0, residual, data, to_nuisance


def first_frame(target) -> int:
    """The first frame in the misfit: the start frame itself when the start state is fitted."""
    return 0 if target.fit_start else 1


def penalty(target: RecordingTarget, r, seen):
    """The loss of residuals `r` (..., 3) where `seen` (...): mean over seen coordinates."""
    if target.loss == "l1":
        values = jnp.abs(r)
    elif target.loss == "huber":
        a, d = jnp.abs(r), target.huber_scale
        values = jnp.where(a <= d, 0.5 * r**2, d * (a - 0.5 * d))
    else:
        values = r**2
    return jnp.sum(values) / jnp.maximum(3.0 * jnp.sum(seen), 1.0)


def loss_function(scene, target: RecordingTarget, names, stage):
    """loss(theta, data) of one stage: direct/ensemble over `stage.frames` frames, or
    shooting segments of `stage.frames` frames each from the start rule's states."""
    model, base = scene.model, scene.params
    if stage.kind in ("direct", "ensemble"):
        misfit = misfit_function(scene, target, names, stage.frames)
        first = first_frame(target)
        return lambda theta, data: penalty(target, misfit(theta, data), data["seen"][:, first : stage.frames + 1])
    length = stage.frames
    firsts = np.arange(0, target.frame_count - 1, length)
    steps = max(_segment_steps(target, int(f), length) for f in firsts)
    picks = np.minimum(firsts[:, None] + np.arange(length + 1)[None], target.frame_count - 1)  # (S, length + 1)

    def one(params, times, x, seen, filled, sx, sv):
        def segment(pick):
            at = times[pick[1:]]
            simulated = markers_simulated(
                model, params, target, times[pick], filled[pick], sx[pick[0]], sv[pick[0]], steps, at
            )
            valid = seen[pick[1:]] & (pick[1:] > pick[:-1])[:, None]  # padding repeats the last frame
            return jnp.where(valid[..., None], simulated - x[pick[1:]], 0.0), valid

        return jax.vmap(segment)(jnp.asarray(picks))

    def loss(theta, data):
        params = model.params_with(base, {n: jnp.exp(theta[n]) for n in names})
        x0, v0 = _start(target, theta, data["states_x"][:, 0], data["states_v"][:, 0])
        sx, sv = data["states_x"].at[:, 0].set(x0), data["states_v"].at[:, 0].set(v0)  # segment 0 from the fitted start
        run = jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0, 0))
        filled = _with_driven(target, theta, data["filled"])
        r, valid = run(params, data["times"], data["x"], data["seen"], filled, sx, sv)
        return penalty(target, r, valid)

    return loss


def residual_function(scene, target: RecordingTarget, names, values: dict):
    """(flat log parameters, unravel, residuals(flat) -> (n,)) over every recording's whole length,
    the start states held (a fitted start: fold it in first, `with_fitted_start`)."""
    from jax.flatten_util import ravel_pytree

    target = dataclasses.replace(target, fit_start=False)
    theta = {n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names}
    flat, unravel = ravel_pytree(theta)
    forward = dataclasses.replace(scene, model=scene.model.forward_mode())  # Jacobians are taken with jacfwd
    misfit = misfit_function(forward, target, names, target.frame_count - 1)
    data = target_data(target)
    return flat, unravel, lambda vector: misfit(unravel(vector), data).reshape(-1)
