"""Multiple shooting with the segments' start states as unknowns.

The horizon is cut into segments of `segment_frames` frames. Each segment starts from a
state of its own (positions and velocities of every free particle), fitted together with
the parameters; a segment's simulated end must meet the next segment's start (a
continuity penalty, raised in turn until it acts as a constraint: `CONTINUITY_WEIGHTS`).
No simulation runs longer than one segment, so each step's model stays smooth in the
parameters however chaotic the whole horizon is (spin, many swings), and positions alone
suffice: start states are guessed from the observed positions (smoothed, velocities from
the smoothing) and then fitted.

Solved by Levenberg-Marquardt on the block structure (`block_lm`, linked blocks): a
segment's residuals depend on the parameters, its own start state and, through the
continuity penalty, the next segment's, so each step eliminates the states along the
chain of segments with one small solve per segment.

`fit.position_shooting` is the variant for recorded states with noisy positions.
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

CONTINUITY_WEIGHTS = (1e2, 1e4, 1e6, 1e8)
"""The continuity penalty's weights, raised in turn, each solve starting from the last one's
answer. A segment's end missing the next segment's start by d [m] (and by w [m/s] in
velocity) costs as much as weight x (d^2 + (w tau)^2) of squared misfit, tau the frame
interval. A light weight first lets the states settle on the data while the parameters are
still wrong; the heavy last one makes continuity a constraint in all but name, so the answer
is the maximum-likelihood fit of one continuous motion (a light penalty lets the states
take up noise as small gaps, which biases the parameters: measured 3-4 standard errors on
the 10 s chain with 1% noise at weight 100 alone). Exact data stop raising as soon as a
raise moves no parameter; with noise every weight runs (`weights_for`: fewer in float32)."""


LIGHT_RANGE = 10.0
"""Until the last continuity weight, every value stays within this factor of its start. At a
light weight the states may take up what a weakly determined parameter does (with noise,
the chain's spring damping over 0.2 s segments): unbounded, its log value drifts towards
minus infinity, where no later weight can bring it back (measured: kd 100% off on a 10 s
chain with 1% noise, from a start 2x off). The last weight's solve is unbounded."""


def weights_for(dtype) -> tuple:
    """The weights of `CONTINUITY_WEIGHTS` the dtype can carry: at weight w the data's share of
    the states' normal matrix is about 1 / w, lost to round-off once w eps nears 1, so
    float32 stops at 1e4 and float64 goes to 1e8."""
    eps = float(jnp.finfo(dtype).eps)
    return tuple(w for w in CONTINUITY_WEIGHTS if w * eps <= 1e-2) or CONTINUITY_WEIGHTS[:1]


SMOOTHING = 3
"""Start-state guesses fit a cubic to the positions of 2 SMOOTHING + 1 frames around the
segment's first one: noisy positions give far fewer stretched springs than raw frames, and
velocities far less noisy than frame differences."""


@dataclasses.dataclass
class SegmentFit:
    """A multiple-shooting fit.

    Attributes:
        values: name -> fitted value.
        starts: the segments' fitted start states, State with x, v (S, N, 3).
        defects: each linked segment's end against the next segment's start, (links, 2): largest
            position gap [m] and velocity gap [m/s].
        history: (cost / residual count, values) before each accepted step (the cost jumps up
            where the continuity weight is raised: each weight is its own objective).
        loss: the shooting objective at the answer: (misfit^2 + weighted gaps^2) / residual count [m^2].
        reduced: the parameters' normal matrix with the states eliminated (for standard errors).
        count: residual values that carry data (observed coordinates).
        unknowns: start-state values estimated besides the parameters.
        segment_frames: frames per segment.
        first_frames: each fitted segment's first frame (S,).
        link_rows: continuity residuals (the links' count times the state size).
        left_out: segments left out because they touch the ground.
        recorded: the segments start from recorded states with their positions fitted and
            their velocities as recorded (`fit_recorded_segments`), not joined.
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
    first_frames: np.ndarray
    link_rows: int
    left_out: int
    recorded: bool = False


def segment_guesses(scene, observations: Observations, segment_frames: int) -> State:
    """Start states (S, N, 3) of the segments from the observations: the recorded states when
    there are any; else positions and velocities of a cubic fitted to 2 SMOOTHING + 1 frames
    around the segment's first (shifted at the ends) of the observed particles' positions, the
    others placed by the start rule (`recordings.spread`) from the target's frame-0 positions."""
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
    window = min(2 * SMOOTHING + 1, frames + 1)
    x, v = [], []
    for f in firsts:
        lo = int(np.clip(f - window // 2, 0, frames + 1 - window))
        t = (np.arange(lo, lo + window) - f) * tau
        fit = np.polyfit(t, np.stack([positions(g).ravel() for g in range(lo, lo + window)]), min(3, window - 1))
        x.append(fit[-1].reshape(rest.shape))
        v.append(fit[-2].reshape(rest.shape) if window > 1 else np.zeros_like(rest))
    dtype = observations.initial_state.x.dtype
    return State(x=jnp.asarray(np.stack(x), dtype=dtype), v=jnp.asarray(np.stack(v), dtype=dtype))


@dataclasses.dataclass
class ShootingProblem:
    """Multiple shooting as linked-block least squares (`block_levenberg_marquardt`).

    Attributes:
        p0: the log parameters (P,); unravel: flat -> {name: log value}.
        s0: the segments' start-state corrections (S, L), zero: s_b is segment b's correction
            to its guess, scaled so that the link gap link_b - s_{b+1} is the weighted
            continuity residual.
        residual: (p, s_b, data_b) -> (r_b, link_b).
        data: the blocks' data, a dict of (S, ...) arrays (`restart` makes new ones).
        to_states: (s, data) -> State (S, N, 3).
        restart: (states, weight) -> data: start from `states` (S, N, 3) with continuity `weight`
            (the same residual function, so compiled code is reused).
        count: residual values that carry data (observed coordinates).
        links: (S,) whether segment b's end is joined to the next block's start.
        first_frames: (S,) each block's first frame (segments touching the ground are left out).
        left_out: how many segments touch the ground and are left out.
    """

    p0: jax.Array
    unravel: object
    s0: jax.Array
    residual: object
    data: dict
    to_states: object
    restart: object
    count: int
    links: np.ndarray
    first_frames: np.ndarray
    left_out: int


def touching(scene, observations: Observations, segment_frames: int, names=()) -> np.ndarray:
    """(S,) which segments touch the ground: an observed particle within a margin of the plane
    at any of the segment's frames (its end included). The margin is one frame's largest
    fall, plus, when some particles are not observed, how far the object reached below its
    lowest observed particle at the start (so a body seen by its top markers still counts
    as landing). All False without a ground, or when a ground parameter is fitted (its
    segments are then needed)."""
    frames, k = observations.frame_count - 1, int(segment_frames)
    firsts = np.arange(0, frames, k)
    if not scene.model.has("ground") or {"kg", "kgd"} & set(names):
        return np.zeros(firsts.size, dtype=bool)
    y = np.asarray(observations.x, dtype=float)[..., 1]  # (F, M)
    fall = np.nanmax(np.abs(np.diff(y, axis=0)), initial=0.0)
    start = np.asarray(observations.initial_state.x, dtype=float)[:, 1]
    below = max(float(np.nanmin(y[0], initial=np.inf) - start.min()), 0.0) if np.isfinite(y[0]).any() else 0.0
    low = np.nanmin(y, axis=1) < float(scene.params.ground_height) + fall + below  # (F,)
    return np.array([low[f : min(f + k, frames) + 1].any() for f in firsts])


def shooting_problem(
    scene, observations: Observations, names, values: dict, segment_frames: int, weight: float, guess=None
) -> ShootingProblem:
    """Multiple shooting of `names` from `values` (`ShootingProblem`), with continuity `weight`
    (`CONTINUITY_WEIGHTS`) and start-state `guess` of the kept segments (State (S, N, 3);
    default `segment_guesses`). Segments that touch the ground (`touching`) are left out:
    contact switches on at a discrete step, which makes their misfit terraced; the
    segments between impacts carry the stiffness, damping and drag, and the chain of
    segments breaks around each impact."""
    model, base = scene.model.forward_mode(), scene.params  # Jacobians are taken with jacfwd
    p0, unravel = ravel_pytree({n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names})
    every, frames, k = observations.save_every, observations.frame_count - 1, int(segment_frames)
    ground = touching(scene, observations, k, names)
    kept = np.nonzero(~ground)[0]
    if kept.size == 0:
        raise InputError(
            "strategy",
            "free_shooting: every segment touches the ground, and contact is left out of its misfit",
            "record states and fit with strategy shooting, or give a recording with motion off the ground",
        )
    if guess is None:
        guess = jax.tree_util.tree_map(lambda a: a[kept], segment_guesses(scene, observations, k))
    count = kept.size
    links = np.append(np.diff(kept) == 1, False)
    free = np.nonzero(~np.asarray(model.pinned, dtype=bool))[0]
    particles = jnp.asarray(observations.particles)
    tau = every * float(model.dt)
    # segment b owns frames bk .. bk + k - 1, and its end too when no segment follows on
    index = kept[:, None] * k + np.arange(k + 1)[None]
    owned = (index <= frames) & ((np.arange(k + 1)[None] < k) | ~links[:, None])
    observed = np.asarray(observations.x)[np.minimum(index, frames)]  # (S, k + 1, M, 3)
    following = np.where(links, np.arange(count) + 1, np.arange(count))

    def restart(states, weight):
        return {
            "x": jnp.asarray(observed),
            "owned": jnp.asarray(owned),
            "gx": states.x,
            "gv": states.v,
            "nx": states.x[following],
            "nv": states.v[following],
            "unit": jnp.full(count, 1.0 / np.sqrt(weight), dtype=states.x.dtype),  # [m] per unit of s
        }

    def start(s_b, d):
        c = s_b.reshape(-1, 6)
        return d["gx"].at[free].add(d["unit"] * c[:, :3]), d["gv"].at[free].add(d["unit"] / tau * c[:, 3:])

    def residual(p, s_b, d):
        params = model.params_with(base, {n: jnp.exp(v) for n, v in unravel(p).items()})
        x0, v0 = start(s_b, d)
        traj = rollout(model, params, State(x=x0, v=v0), steps=k * every, save_every=every)
        r = jnp.where(d["owned"][:, None, None], traj.x[:, particles] - d["x"], 0.0).reshape(-1)
        gap_x, gap_v = (traj.x[-1] - d["nx"])[free], (traj.v[-1] - d["nv"])[free] * tau
        return r, (jnp.concatenate([gap_x, gap_v], axis=1) / d["unit"]).reshape(-1)

    def to_states(s, data):
        x, v = jax.vmap(start)(jnp.asarray(s), data)
        return State(x=x, v=v)

    s0 = jnp.zeros((count, free.size * 6), dtype=guess.x.dtype)
    count_data = int(owned.sum()) * particles.size * 3
    data = restart(guess, weight)
    return ShootingProblem(
        p0, unravel, s0, residual, data, to_states, restart, count_data, links, kept * k, int(ground.sum())
    )


def values_of(unravel, p) -> dict:
    return {n: np.asarray(jnp.exp(x)) for n, x in unravel(jnp.asarray(p)).items()}


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
    problem = shooting_problem(scene, observations, names, values, segment_frames, CONTINUITY_WEIGHTS[0])
    p, guess, history = problem.p0, None, []
    weights = weights_for(problem.s0.dtype)
    light = (problem.p0 - np.log(LIGHT_RANGE), problem.p0 + np.log(LIGHT_RANGE))
    for stage, weight in enumerate(weights):
        data = problem.restart(guess, weight) if stage else problem.data
        solution = block_levenberg_marquardt(
            problem.residual,
            p,
            problem.s0,
            data,
            iterations=iterations,
            tolerance=tolerance,
            linked=problem.links,
            bounds=light if stage < len(weights) - 1 else None,
        )
        history += [(cost / problem.count, values_of(problem.unravel, p)) for cost, p in solution.history]
        moved, p = np.max(np.abs(solution.p - p), initial=0.0), solution.p
        guess = problem.to_states(solution.s, data)
        if stage and moved <= tolerance:  # raising the weight changed nothing
            break
    values = values_of(problem.unravel, p)
    model = scene.model
    params = model.params_with(scene.params, values)
    steps = int(segment_frames) * observations.save_every
    joined = np.nonzero(problem.links)[0]  # segments whose end meets the next one's start
    defects = np.zeros((joined.size, 2))
    if joined.size:
        end = jax.vmap(lambda x, v: final_state(model, params, State(x=x, v=v), steps))(
            guess.x[joined], guess.v[joined]
        )
        defects[:, 0] = np.abs(np.asarray(end.x - guess.x[joined + 1])).max(axis=(1, 2))
        defects[:, 1] = np.abs(np.asarray(end.v - guess.v[joined + 1])).max(axis=(1, 2))
    return SegmentFit(
        values=values,
        starts=guess,
        defects=defects,
        history=history,
        loss=solution.cost / problem.count,
        reduced=solution.reduced,
        count=problem.count,
        unknowns=int(problem.s0.size),
        segment_frames=int(segment_frames),
        first_frames=problem.first_frames,
        link_rows=int(problem.links.sum()) * problem.s0.shape[1],
        left_out=problem.left_out,
    )
