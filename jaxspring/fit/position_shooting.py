"""Multiple shooting from recorded states whose positions are noisy (strategy
"position_shooting"): segments from the recorded states, not joined, each with its start
positions fitted with the parameters and its velocities as recorded."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..errors import InputError
from ..sim.rollout import rollout
from ..sim.state import State
from .block_lm import block_levenberg_marquardt
from .observations import Observations
from .shooting import SegmentFit, _values


def fit_recorded_segments(
    scene,
    observations: Observations,
    names,
    values: dict,
    segment_frames: int = 10,
    iterations: int = 100,
    tolerance: float = 1e-10,
) -> SegmentFit:
    """Fit `names` from `values` by multiple shooting from recorded states whose positions are
    noisy: each segment starts from its recorded state with the free particles' positions
    fitted too (the recorded positions of its first frame are one more frame of its data),
    and the recorded velocities as they are.

    Started from noisy recorded positions as they are, every segment sets off elastic
    oscillations the true parameters do not explain, and damping is fitted to hide them
    (errors in variables; measured on the 7 x 6 x 5 jelly over 1 s with 1% noise: kd 0.35-75x
    its truth). Fitting the start positions removes that bias. The segments are not joined
    (each is its own motion from its own start), so the blocks are independent, and each
    holds hundreds of start values: its J_s^T J_s only preconditions the solves (`frozen`).
    Segments touching the ground are kept (unlike `fit_segments`'s): a jelly's damping shows
    mostly in how its impacts ring down.

    Example:
        >>> fit = fit_recorded_segments(scene, obs, ["ks", "kd"], {"ks": 250.0, "kd": 0.3})
        >>> fit.values
    """
    if observations.states is None:
        raise InputError("strategy", "needs recorded states of every particle", "use free_shooting")
    model, base = scene.model.forward_mode(), scene.params  # Jacobians are taken with jacfwd
    p0, unravel = ravel_pytree({n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names})
    every, frames, k = observations.save_every, observations.frame_count - 1, int(segment_frames)
    firsts = np.arange(0, frames, k)
    count = firsts.size
    # segment b owns frames bk .. bk + k - 1 (its first one: its start's recorded positions), the
    # last one its end too
    index = firsts[:, None] + np.arange(k + 1)[None]
    owned = (index <= frames) & ((np.arange(k + 1)[None] < k) | (np.arange(count) == count - 1)[:, None])
    free = np.nonzero(~np.asarray(model.pinned, dtype=bool))[0]
    particles = jnp.asarray(observations.particles)
    states = observations.states
    data = {
        "x": jnp.asarray(np.asarray(observations.x)[np.minimum(index, frames)]),
        "owned": jnp.asarray(owned),
        "gx": jnp.asarray(states.x)[firsts],
        "gv": jnp.asarray(states.v)[firsts],
    }

    def start(s_b, d):
        return d["gx"].at[free].add(s_b.reshape(-1, 3))

    def residual(p, s_b, d):
        params = model.params_with(base, {n: jnp.exp(v) for n, v in unravel(p).items()})
        traj = rollout(model, params, State(x=start(s_b, d), v=d["gv"]), steps=k * every, save_every=every)
        return jnp.where(d["owned"][:, None, None], traj.x[:, particles] - d["x"], 0.0).reshape(-1)

    s0 = jnp.zeros((count, free.size * 3), dtype=data["gx"].dtype)
    solution = block_levenberg_marquardt(residual, p0, s0, data, iterations, tolerance, frozen=True)
    data_count = int(owned.sum()) * particles.size * 3
    starts = State(x=jax.vmap(start)(jnp.asarray(solution.s), data), v=data["gv"])
    return SegmentFit(
        values=_values(unravel, solution.p),
        starts=starts,
        defects=np.zeros((0, 2)),
        history=[(cost / data_count, _values(unravel, q)) for cost, q in solution.history],
        loss=solution.cost / data_count,
        reduced=solution.reduced,
        count=data_count,
        unknowns=int(s0.size),
        segment_frames=k,
        first_frames=firsts,
        link_rows=0,
        left_out=0,
        recorded=True,
    )
