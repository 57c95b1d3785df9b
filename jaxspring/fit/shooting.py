"""Multiple shooting with the segments' start states as unknowns.

The horizon is cut into segments of `segment_frames` frames. Each segment starts from a
state of its own (positions and velocities of every free particle), fitted together with
the parameters; a segment's simulated end must meet the next segment's start (a
continuity penalty, `CONTINUITY_WEIGHT`). No simulation runs longer than one segment, so
the misfit stays smooth in the parameters however chaotic the whole horizon is (contact,
spin), and positions alone suffice: start states are guessed from the observed positions
(velocities by differences) and then fitted.

Solved by Levenberg-Marquardt on the block structure (`block_lm`, linked blocks): a
segment's residuals depend on the parameters, its own start state and, through the
continuity penalty, the next segment's, so each step eliminates the states along the
chain of segments with one small solve per segment.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..errors import InputError
from ..sim.rollout import final_state, rollout
from ..sim.state import State
from .observations import Observations
from .recordings import spread

CONTINUITY_WEIGHT = 100.0
"""A segment's end missing the next segment's start by d [m] (and by w [m/s] in velocity)
costs as much as CONTINUITY_WEIGHT x (d^2 + (w tau)^2) of squared misfit, tau the frame
interval: continuity nearly as a constraint, while intermediate iterates may break it."""


@dataclasses.dataclass
class SegmentFit:
    """A multiple-shooting fit.

    Attributes:
        values: name -> fitted value.
        starts: the segments' fitted start states, State with x, v (S, N, 3).
        defects: each segment's end against the next segment's start, (S - 1, 2): largest
            position gap [m] and velocity gap [m/s].
        history: (cost / residual count, values) before each accepted step.
        loss: the shooting objective at the answer: (misfit^2 + weighted gaps^2) / residual count [m^2].
        reduced: the parameters' normal matrix with the states eliminated (for standard errors).
        count: residual values that carry data (observed coordinates).
        unknowns: start-state values estimated besides the parameters.
        segment_frames: frames per segment.
    """

    values: dict
    starts: State
    defects: np.ndarray
    history: list
    loss: float
    reduced: np.ndarray
    count: int
    unknowns: int
    segment_frames: int


def segment_guesses(scene, observations: Observations, segment_frames: int) -> State:
    """Start states (S, N, 3) of the segments from the observations: the recorded states when
    there are any; else the observed particles' positions, the others placed by the start
    rule (`recordings.spread`) from the target's frame-0 positions, and velocities by central
    differences of those positions (one-sided at the ends)."""
    frames = observations.frame_count - 1
    firsts = np.arange(0, frames, segment_frames)
    if observations.states is not None:
        return State(x=jnp.asarray(observations.states.x)[firsts], v=jnp.asarray(observations.states.v)[firsts])
    pinned = np.asarray(scene.model.pinned, dtype=bool)
    rest = np.asarray(observations.initial_state.x, dtype=float)
    particles = np.asarray(observations.particles)

    def positions(frame):
        out = spread(rest, particles, np.asarray(observations.x[frame], dtype=float))
        out[pinned] = rest[pinned]
        return out

    tau = observations.save_every * float(scene.model.dt)
    x, v = [], []
    for f in firsts:
        before, after = max(f - 1, 0), min(f + 1, frames)
        x.append(positions(f))
        v.append((positions(after) - positions(before)) / ((after - before) * tau))
    dtype = observations.initial_state.x.dtype
    return State(x=jnp.asarray(np.stack(x), dtype=dtype), v=jnp.asarray(np.stack(v), dtype=dtype))


def shooting_problem(scene, observations: Observations, names, values: dict, segment_frames: int):
    """The fit as linked-block least squares (`block_levenberg_marquardt(..., linked=True)`).

    Returns (p0, unravel, s0 (S, L), residual(p, s_b, data_b) -> (r_b, link_b), data,
    to_states(s) -> State, count: residual values that carry data).
    s_b holds segment b's start-state corrections to its guess, scaled so that the link gap
    link_b - s_{b+1} is the weighted continuity residual."""
    model, base = scene.model.forward_mode(), scene.params  # Jacobians are taken with jacfwd
    p0, unravel = ravel_pytree({n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names})
    every, frames, k = observations.save_every, observations.frame_count - 1, int(segment_frames)
    guess = segment_guesses(scene, observations, k)
    count = guess.x.shape[0]
    free = np.nonzero(~np.asarray(model.pinned, dtype=bool))[0]
    particles = jnp.asarray(observations.particles)
    tau = every * float(model.dt)
    unit_x = 1.0 / np.sqrt(CONTINUITY_WEIGHT)  # [m] per unit of s
    unit_v = unit_x / tau  # [m/s] per unit of s
    # segment b owns frames bk .. bk + k - 1 (the last one also its end when that is the last frame)
    index = np.arange(count)[:, None] * k + np.arange(k + 1)[None]
    owned = (index <= frames) & ((np.arange(k + 1)[None] < k) | (index == frames))
    observed = np.asarray(observations.x)[np.minimum(index, frames)]  # (S, k + 1, M, 3)
    following = np.minimum(np.arange(count) + 1, count - 1)
    data = {
        "x": jnp.asarray(observed),
        "owned": jnp.asarray(owned),
        "gx": guess.x,
        "gv": guess.v,
        "nx": guess.x[following],
        "nv": guess.v[following],
    }

    def start(s_b, d):
        c = s_b.reshape(-1, 6)
        return d["gx"].at[free].add(unit_x * c[:, :3]), d["gv"].at[free].add(unit_v * c[:, 3:])

    def residual(p, s_b, d):
        params = model.params_with(base, {n: jnp.exp(v) for n, v in unravel(p).items()})
        x0, v0 = start(s_b, d)
        traj = rollout(model, params, State(x=x0, v=v0), steps=k * every, save_every=every)
        r = jnp.where(d["owned"][:, None, None], traj.x[:, particles] - d["x"], 0.0).reshape(-1)
        ahead = jnp.concatenate([(traj.x[-1] - d["nx"])[free] / unit_x, (traj.v[-1] - d["nv"])[free] / unit_v], axis=1)
        return r, ahead.reshape(-1)

    def to_states(s):
        x, v = jax.vmap(start)(jnp.asarray(s), data)
        return State(x=x, v=v)

    s0 = jnp.zeros((count, free.size * 6), dtype=guess.x.dtype)
    return p0, unravel, s0, residual, data, to_states, int(owned.sum()) * particles.size * 3


def fit_segments(
    scene,
    observations: Observations,
    names,
    values: dict,
    segment_frames: int = 10,
    iterations: int = 50,
    tolerance: float = 1e-10,
) -> SegmentFit:
    """Fit `names` from `values` by multiple shooting with free segment start states (module docstring).

    Example:
        >>> fit = fit_segments(scene, obs, ["ks", "kd"], {"ks": 400.0, "kd": 0.2}, segment_frames=10)
        >>> fit.values, fit.defects.max(axis=0)
    """
    from .block_lm import block_levenberg_marquardt

    if int(segment_frames) < 1:
        raise InputError("segment_frames", "must be >= 1", "set e.g. segment_frames = 10")
    problem = shooting_problem(scene, observations, names, values, segment_frames)
    p0, unravel, s0, residual, data, to_states, count = problem
    solution = block_levenberg_marquardt(
        residual, p0, s0, data, iterations=iterations, tolerance=tolerance, linked=True
    )
    to_values = lambda v: {n: np.asarray(jnp.exp(x)) for n, x in unravel(jnp.asarray(v)).items()}  # noqa: E731
    starts = to_states(solution.s)
    model = scene.model
    params = model.params_with(scene.params, to_values(solution.p))
    steps = int(segment_frames) * observations.save_every
    defects = np.zeros((0, 2))
    if starts.x.shape[0] > 1:
        end = jax.vmap(lambda x, v: final_state(model, params, State(x=x, v=v), steps))(starts.x[:-1], starts.v[:-1])
        gap_x = np.abs(np.asarray(end.x - starts.x[1:])).max(axis=(1, 2))
        gap_v = np.abs(np.asarray(end.v - starts.v[1:])).max(axis=(1, 2))
        defects = np.stack([gap_x, gap_v], axis=1)
    history = [(cost / count, to_values(p)) for cost, p in solution.history]
    return SegmentFit(
        values=to_values(solution.p),
        starts=starts,
        defects=defects,
        history=history,
        loss=solution.cost / count,
        reduced=solution.reduced,
        count=count,
        unknowns=int(s0.size),
        segment_frames=int(segment_frames),
    )


def free_shooting_stage(scene, observations, names, stage, settings, progress) -> list[SegmentFit]:
    """A plan's "free_shooting" stage: `fit_segments` for every member of `progress` from its
    current values; appends the accepted steps to the history and leaves the answers in
    `progress.theta`. Returns each member's SegmentFit."""
    members = int(np.shape(progress.theta[names[0]])[0])
    fits = []
    for m in range(members):
        target = observations[m if len(observations) > 1 else 0]
        values = {n: np.exp(np.asarray(progress.theta[n][m], dtype=float)) for n in names}
        fits.append(
            fit_segments(scene, target, names, values, stage.frames, settings.iterations, settings.step_tolerance)
        )
    for i in range(max(len(f.history) for f in fits)):  # members that finished early repeat their answer
        entries = [f.history[i] if i < len(f.history) else (f.loss, f.values) for f in fits]
        progress.loss.append(np.array([loss for loss, _ in entries]))
        for n in names:
            progress.values[n].append(np.stack([np.asarray(v[n]) for _, v in entries]))
        progress.stage_of_iteration.append(progress.stage)
    progress.theta = {n: jnp.stack([jnp.log(jnp.asarray(f.values[n])) for f in fits]) for n in names}
    return fits


def describe(fit: SegmentFit) -> str:
    """The objective a SegmentFit minimises, in words (for the identifiability report)."""
    segments = fit.starts.x.shape[0]
    return (
        f"multiple shooting: the misfit of {segments} segments of {fit.segment_frames} frames, each from a "
        f"fitted start state (largest continuity gap {fit.defects[:, 0].max(initial=0.0):.2g} m)"
    )
