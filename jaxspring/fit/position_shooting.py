"""Multiple shooting from recorded states whose positions are noisy (strategy
"position_shooting"): segments from the recorded states, not joined, each with its start
positions fitted with the parameters and its velocities as recorded. Also the plan's stages
that fit segment states (this kind, or "free_shooting" from `shooting`) over a fit's members."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..errors import InputError
from ..sim.rollout import rollout
from ..sim.state import State
from .block_lm import block_levenberg_marquardt
from .observations import Observations
from .shooting import SegmentFit, fit_segments, values_of


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
    seg = _recorded_segments(scene, observations, names, values, segment_frames)
    s0 = jnp.zeros((seg.firsts.size, seg.free.size * 3), dtype=seg.data["gx"].dtype)
    solution = block_levenberg_marquardt(seg.residual, seg.p0, s0, seg.data, iterations, tolerance, frozen=True)
    data_count = int(seg.owned.sum()) * seg.observed * 3
    starts = State(x=jax.vmap(seg.start)(jnp.asarray(solution.s), seg.data), v=seg.data["gv"])
    return SegmentFit(
        values=values_of(seg.unravel, solution.p),
        starts=starts,
        defects=np.zeros((0, 2)),
        history=[(cost / data_count, values_of(seg.unravel, q)) for cost, q in solution.history],
        loss=solution.cost / data_count,
        reduced=solution.reduced,
        count=data_count,
        unknowns=int(s0.size),
        segment_frames=seg.frames,
        first_frames=seg.firsts,
        link_rows=0,
        left_out=0,
        recorded=True,
    )


NOISE_SEGMENTS = 3
"""Segments, spread over the target, whose start positions `start_fitted_noise` fits."""

NOISE_STEPS = 2
"""Gauss-Newton steps `start_fitted_noise` takes: the start positions enter the motion almost
linearly, so the first step does nearly all (on the 0.7 s jelly with 1% noise the second
moves a segment's residual sum of squares by at most 0.2%)."""

NOISE_CG_TOLERANCE = 1e-8
"""Relative residual at which conjugate gradients stop on each step's normal equations in
`start_fitted_noise` (the 7 x 6 x 5 jelly's segments take 10-20 iterations), or 100 times
the central differences' accuracy (eps^(2/3)) where that is larger (float32)."""

NOISE_CG_ITERATIONS = 100
"""Most conjugate-gradient iterations per step in `start_fitted_noise`."""


def start_fitted_noise(
    scene, observations: Observations, names, values: dict, segment_frames: int = 10
) -> tuple[float, int]:
    """(variance [m^2], degrees of freedom) of the recorded positions' noise, estimated from
    `NOISE_SEGMENTS` segments of `segment_frames` frames from the recorded states with their
    start positions fitted and the parameters held at `values`: their residual sum of
    squares over the data values less the fitted start values.

    The starts' noise does not enter it (the starts are fitted), and a short segment hardly
    depends on what a long one determines (kd of a bouncing jelly), so values in a wrong dip
    of a long horizon's misfit still leave about the noise here. Measured on the 7 x 6 x 5
    jelly over 1 s with 1% noise: 1.00, 1.00 and 1.04 times the variance drawn, at the truth
    and at kd 7x and 22x its truth (a synthetic target's first frame is exact, which the
    first segment counts as noise: about 3% low for 10-frame segments). It runs on the
    scene's own backend
    and forms no Jacobian (`_start_fitted_squares`): 1 s on that jelly over 0.7 s, where
    the forward-mode Jacobian of its 630 start coordinates took 14 s.

    Example:
        >>> variance, freedom = start_fitted_noise(scene, obs, ["ks", "kd"], {"ks": 250.0, "kd": 0.05})
    """
    seg = _recorded_segments(scene, observations, names, values, segment_frames)
    count, unknowns = seg.firsts.size, seg.free.size * 3
    model, every = scene.model, observations.save_every
    params = model.params_with(scene.params, {n: jnp.asarray(values[n], dtype=float) for n in names})
    fixed = (model, params, jnp.asarray(observations.particles), jnp.asarray(seg.free))
    squares, freedom = 0.0, 0
    for b in np.unique(np.linspace(0, count - 1, min(NOISE_SEGMENTS, count)).round().astype(int)):
        data = {key: value[b] for key, value in seg.data.items()}
        squares += float(_start_fitted_squares(*fixed, data, frames=seg.frames, every=every))
        freedom += int(seg.owned[b].sum()) * seg.observed * 3 - unknowns
    return squares / max(freedom, 1), max(freedom, 1)


@functools.partial(jax.jit, static_argnames=("frames", "every"))
def _start_fitted_squares(model, params, particles, free, data, frames, every):
    """One segment's residual sum of squares with its start positions fitted and `params`
    held: `NOISE_STEPS` Gauss-Newton steps from the recorded start, each solving its normal
    equations J^T J ds = -J^T r by conjugate gradients without forming J (hundreds of
    columns): J v by central differences of the segment's motion, J^T u by its reverse pass,
    so the native kernel (reverse mode only) runs it. An inexact step leaves the sum of
    squares above its minimum by |J e|^2 for a step error e, second order. A function of
    arrays only, so one compiled copy serves every segment, member and call."""

    def residual(s_b):
        return _segment_misfit(model, params, particles, free, s_b, data, frames, every)

    s = jnp.zeros(free.size * 3, dtype=data["gx"].dtype)
    eps = float(jnp.finfo(s.dtype).eps)
    # the step of a central difference: round-off and truncation balanced, relative to the positions
    size = jnp.max(jnp.abs(data["gx"]))
    h = eps ** (1 / 3) * jnp.where(size > 0, size, 1.0)
    tolerance = max(NOISE_CG_TOLERANCE, 100 * eps ** (2 / 3))
    for _ in range(NOISE_STEPS):
        r, pullback = jax.vjp(residual, s)

        def normal(v, s=s, pullback=pullback):  # J^T J v
            length = jnp.linalg.norm(v)
            u = v / jnp.where(length > 0, length, 1.0)
            return pullback(length * (residual(s + h * u) - residual(s - h * u)) / (2 * h))[0]

        step, _ = jax.scipy.sparse.linalg.cg(normal, -pullback(r)[0], tol=tolerance, maxiter=NOISE_CG_ITERATIONS)
        s = s + step
    return jnp.sum(residual(s) ** 2)


@dataclasses.dataclass(frozen=True)
class _Segments:
    """Segments of `frames` frames from the recorded states, each starting at a recorded
    state with its free particles' positions offset by its block of unknowns (`start`), and
    their misfit (`residual(p, s_b, data_b)`: p the log parameter values, packed)."""

    p0: jax.Array
    unravel: object
    residual: object
    start: object
    data: dict
    owned: np.ndarray
    firsts: np.ndarray
    free: np.ndarray
    observed: int
    frames: int


def _recorded_segments(scene, observations: Observations, names, values: dict, segment_frames: int) -> _Segments:
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

    def residual(p, s_b, d):
        params = model.params_with(base, {n: jnp.exp(v) for n, v in unravel(p).items()})
        return _segment_misfit(model, params, particles, free, s_b, d, k, every)

    start = functools.partial(_segment_start, free)
    return _Segments(p0, unravel, residual, start, data, owned, firsts, free, int(particles.size), k)


def _segment_start(free, s_b, d):
    """A segment's start positions: its recorded ones, the free particles' offset by s_b."""
    return d["gx"].at[free].add(s_b.reshape(-1, 3))


def _segment_misfit(model, params, particles, free, s_b, d, frames, every):
    """A segment's misfit to its owned frames, from its recorded start with the free
    particles' positions offset by s_b and its recorded velocities, flattened."""
    traj = rollout(
        model, params, State(x=_segment_start(free, s_b, d), v=d["gv"]), steps=frames * every, save_every=every
    )
    return jnp.where(d["owned"][:, None, None], traj.x[:, particles] - d["x"], 0.0).reshape(-1)


def segment_fitter(kind: str):
    """The fit of a stage of `kind` that fits the segments' states: "free_shooting"
    (`fit_segments`) or "position_shooting" (`fit_recorded_segments`)."""
    return fit_recorded_segments if kind == "position_shooting" else fit_segments


def member_segment_fits(scene, observations, names, stage, settings, theta: dict) -> list[SegmentFit]:
    """A segment-state stage's fit (`segment_fitter`) of every member from its log values in
    `theta` (name -> (B, ...)); `observations` holds one target, or one per member."""
    fit_of = segment_fitter(stage.kind)
    fits = []
    for m in range(int(np.shape(theta[names[0]])[0])):
        target = observations[m if len(observations) > 1 else 0]
        values = {n: np.exp(np.asarray(theta[n][m], dtype=float)) for n in names}
        fits.append(fit_of(scene, target, names, values, stage.frames, settings.iterations, settings.step_tolerance))
    return fits


def free_shooting_stage(scene, observations, names, stage, settings, progress) -> list[SegmentFit]:
    """A plan's "free_shooting" stage (`fit_segments`) or "position_shooting" stage
    (`fit_recorded_segments`) for every member of `progress` from its current values; appends
    the accepted steps to the history and leaves the answers in `progress.theta`. Returns each
    member's SegmentFit."""
    fits = member_segment_fits(scene, observations, names, stage, settings, progress.theta)
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
    if fit.recorded:
        return (
            f"multiple shooting: the misfit of {segments} segments of {fit.segment_frames} frames, each from its "
            "recorded state with the positions fitted (the recorded ones are one more frame of data) and the "
            "velocities as recorded"
        )
    left_out = f"; {fit.left_out} touching the ground left out" if fit.left_out else ""
    gap = f"largest continuity gap {fit.defects[:, 0].max():.2g} m" if len(fit.defects) else "none joined"
    return (
        f"multiple shooting: the misfit of {segments} segments of {fit.segment_frames} frames, each from a "
        f"fitted start state ({gap}{left_out})"
    )
