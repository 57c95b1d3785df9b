"""How many frames of a target the misfit stays smooth over: the objective's horizon.

Over a chaotic motion (a spinning jelly bouncing several times) or many swings, the
simulated motion soon depends on the parameters so sensitively that the whole-horizon
misfit is a landscape of dips and walls, and a stage that polishes there can walk away
from a perfect answer. The test here asks the model itself. From recorded states along
the target it simulates a cloud of parameter values around the current ones (a symmetric
set of normal points of standard deviation `spread` in log space, as the ensemble stage
draws them) and fits each frame's positions across the cloud with a linear function of
the parameters. Over a stretch of F frames,

    nonlinearity(F) = sqrt(sum_f |what the linear fit leaves| ^ 2 / sum_f |what it explains| ^ 2)

The misfit over a stretch is smooth at that scale while the nonlinearity stays below
`NONLINEARITY_LIMIT`; the horizon is the longest such stretch from every start. Contact
switching on at discrete steps cuts small dips into the misfit, which the cloud's linear
fit averages over (as the ensemble stage does); chaos, where a change of the parameters
sends the motion anywhere, the linear fit cannot explain.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..sim.rollout import rollout
from ..sim.scene import Scene
from ..sim.state import State
from .observations import Observations

NONLINEARITY_LIMIT = 0.5
"""Largest nonlinearity (the module's docstring) at which a stretch still counts as smooth:
what the linear fit leaves is at most half what it explains (in norm). A value the motion
depends on exactly linearly still leaves the curvature of exp: 0.2 at a spread of 30%,
0.07 at 10%."""

ROUND_OFF = 64
"""Motion the cloud moves by less than this many units of round-off (of the positions' size)
carries no information on smoothness: such stretches count as smooth, not as noise."""

STARTS = 8
"""Recorded states the test starts from, evenly spread over the target."""


@dataclasses.dataclass(frozen=True)
class Horizon:
    """The result of `smooth_horizon`.

    Attributes:
        frames: the longest stretch [frames] over which the misfit is smooth at `spread`
            from every start (at least 1; `total` when the whole target is).
        total: the target's frames after frame 0.
        spread: the log-parameter change the test moved each value by.
        starts: the frames the test started from, (S,).
        nonlinearity: per start and stretch length, (S, total); NaN where a stretch runs
            past the target's end.
    """

    frames: int
    total: int
    spread: float
    starts: np.ndarray
    nonlinearity: np.ndarray

    @property
    def whole(self) -> bool:
        """Whether the whole target is smooth at `spread`."""
        return self.frames >= self.total

    def describe(self) -> str:
        """The finding in words, for the fit report."""
        return describe_smoothness(self.frames, self.total, self.spread)


def round_off_loss(scene: Scene, observations: Observations) -> float:
    """The loss [m^2] of positions that differ by round-off alone (`ROUND_OFF` units of the
    scene's precision, of the target's size): a stage that reaches it has nothing left to fit.

    Example:
        >>> round_off_loss(scene, obs)  # about 1e-26 m^2 for a float64 jelly
    """
    size = float(np.nanmax(np.abs(np.asarray(observations.x, dtype=float)), initial=1.0))
    return (ROUND_OFF * float(jnp.finfo(scene.model.mass.dtype).eps) * size) ** 2


def describe_smoothness(frames: int, total: int, spread: float) -> str:
    """A measured horizon in words: smooth at `spread` (log) over `frames` of `total` frames.

    Example:
        >>> describe_smoothness(62, 250, 0.1)
        'the motion stays smooth in the parameters at 11% over 62 frames, not over all 250'
    """
    percent = f"{100 * (np.exp(spread) - 1):.0f}%"
    if frames >= total:
        return f"the motion stays smooth in the parameters at {percent} over all {total} frames"
    return f"the motion stays smooth in the parameters at {percent} over {frames} frames, not over all {total}"


def describe_segments(segment: int | None, total: int, horizon: int, spread: float) -> str:
    """What a final stage fitted to a measured `horizon` minimises, in words (the report's
    objective): the whole horizon (`segment` None), or `segment`-frame segments from
    recorded states.

    Example:
        >>> describe_segments(50, 250, 62, 0.1)  # 'the misfit over 5 segments of 50 frames, ...'
    """
    smooth = describe_smoothness(horizon, total, spread)
    if not segment or segment >= total:
        return f"the misfit over the whole horizon ({smooth})"
    return (
        f"the misfit over {total // segment} segments of {segment} frames, each from its recorded start state "
        f"({smooth}; {total - (total // segment) * segment} trailing frames left out)"
    )


def smooth_horizon(
    scene: Scene,
    observations: Observations,
    names,
    values: dict,
    spread: float = 0.1,
    limit: float = NONLINEARITY_LIMIT,
    starts: int = STARTS,
    members: int = 16,
    cloud=None,
) -> Horizon:
    """The longest stretch of `observations` over which the misfit is smooth in `names` at `spread`.

    Simulates from up to `starts` recorded states (from the known initial state alone when
    only positions were recorded) a cloud of `members` parameter values around `values`
    (standard deviation `spread` in log space; every entry of a per-spring parameter moves
    together), and finds the longest stretch whose nonlinearity (module docstring) stays
    below `limit` from every start. No gradients: the scene's fastest backend runs it.

    Args:
        scene: the model and its other parameters.
        observations: the target; its recorded states (if any) are the starts.
        names: fitted parameter names.
        values: name -> value (positive) to test at.
        spread: the parameter change [log] the misfit must stay smooth over.
        limit: largest nonlinearity counted as smooth.
        starts: most start frames.
        members: cloud size (even).
        cloud: the cloud's offsets from `values` in log space, (K, P) in `names` order,
            in place of the drawn one (`spread` and `members` then unused).
    Returns:
        Horizon.

    Example:
        >>> h = smooth_horizon(scene, obs, ["ks", "kd"], {"ks": 250.0, "kd": 0.05})
        >>> h.frames, h.describe()
    """
    names = tuple(names)
    total = observations.frame_count - 1
    every = observations.save_every
    dtype = scene.model.mass.dtype
    if observations.states is not None:
        first = np.unique(np.linspace(0, total, max(1, min(starts, total)), endpoint=False).astype(int))
        x0 = jnp.asarray(observations.states.x, dtype)[first]
        v0 = jnp.asarray(observations.states.v, dtype)[first]
    else:
        first = np.zeros(1, dtype=int)
        x0 = jnp.asarray(observations.initial_state.x, dtype)[None]
        v0 = jnp.asarray(observations.initial_state.v, dtype)[None]
    if cloud is None:
        half = np.random.default_rng(0).standard_normal((max(members // 2, len(names) + 1), len(names)))
        cloud = spread * np.concatenate([half, -half])
    offsets = np.asarray(cloud, dtype=float).reshape(-1, len(names))
    cloud = jnp.asarray(offsets, dtype)
    design = jnp.asarray(offsets - offsets.mean(axis=0), dtype)  # regression with an intercept
    centre = {n: jnp.log(jnp.asarray(values[n], dtype)) for n in names}
    particles = jnp.asarray(observations.particles)
    model, base = scene.model, scene.params

    @jax.jit
    def curves(x, v):
        def run(offset):
            moved = {n: jnp.exp(centre[n] + offset[i]) for i, n in enumerate(names)}
            params = model.params_with(base, moved)
            return rollout(model, params, State(x=x, v=v), steps=total * every, save_every=every).x[1:, particles]

        paths = jax.vmap(run)(cloud)  # (K, total, M, 3)
        paths = (paths - paths.mean(axis=0)).reshape(cloud.shape[0], -1)
        fitted = design @ jnp.linalg.lstsq(design, paths)[0]  # the linear part, per coordinate
        per_frame = lambda a: jnp.sum(a.reshape(cloud.shape[0], total, -1) ** 2, axis=(0, 2))  # noqa: E731
        return jnp.cumsum(per_frame(fitted)), jnp.cumsum(per_frame(paths - fitted))

    nonlinearity = np.full((first.size, total), np.nan)
    frames = total
    size = float(np.max(np.abs(np.asarray(x0)), initial=1.0))
    entries = cloud.shape[0] * int(particles.size) * 3  # per frame
    round_off = entries * np.arange(1, total + 1) * (ROUND_OFF * float(jnp.finfo(dtype).eps) * size) ** 2
    for row, start in enumerate(first):
        explained, left = (np.asarray(a, dtype=float) for a in curves(x0[row], v0[row]))
        length = total - int(start)  # stretches that stay within the target
        explained, left = explained[:length], left[:length]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.sqrt(left / explained)
        ratio = np.where(explained > round_off[:length], ratio, 0.0)  # motion the values barely move
        ratio = np.where(np.isfinite(explained) & np.isfinite(left), ratio, np.inf)  # a cloud member blew up
        nonlinearity[row, :length] = ratio
        beyond = np.nonzero(ratio > limit)[0]
        if beyond.size:
            frames = min(frames, max(int(beyond[0]), 1))
    return Horizon(frames=int(frames), total=total, spread=float(spread), starts=first, nonlinearity=nonlinearity)


def measure_horizon(scene: Scene, observations: list, names, spread: float, theta: dict) -> int:
    """The frames [int] over which every member's misfit stays smooth at `spread`, measured
    at its values (`theta`: name -> log values, (B, ...); `observations`: one target, or one
    per member).

    Example:
        >>> measure_horizon(scene, [obs], ["ks"], 0.1, {"ks": jnp.log(jnp.array([250.0]))})
    """
    frames = []
    for member in range(np.shape(theta[names[0]])[0]):
        values = {n: np.exp(np.asarray(theta[n][member], dtype=float)) for n in names}
        target = observations[member if len(observations) > 1 else 0]
        frames.append(smooth_horizon(scene, target, names, values, spread=spread).frames)
    return min(frames)
