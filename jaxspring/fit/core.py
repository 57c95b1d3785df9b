"""Parameter identification: fit physical parameters by differentiating through rollouts.

The fit minimises the mean squared position error over the observed particles and
frames. Positive parameters are optimised in log space. Long targets are fitted in
stages: a horizon curriculum (short, then longer) or multiple shooting (short
segments started from recorded states) followed by a full-horizon stage, so the
final answer is always a full-horizon least-squares fit. Where contact makes the
loss rough, that last stage is an ensemble Gauss-Newton on the loss smoothed at the
scale of the parameters' own uncertainty (see `FitSettings.ensemble`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from ..errors import InputError
from ..fit.observations import Observations
from ..io.scene import Scene
from ..sim.params import NON_NEGATIVE
from ..sim.rollout import rollout
from ..sim.sharding import shard_batch
from ..sim.state import State

FITTABLE = NON_NEGATIVE  # ks, kd, cd, kg, kgd: positive, fitted in log space
OPTIMIZERS = ("lbfgs", "adam")
STRATEGIES = ("auto", "direct", "curriculum", "shooting")
ENSEMBLE_CHOICES = ("auto", "gradient", "ensemble")
ENSEMBLE_MAX_PARAMETERS = 8  # scalar values; a Gaussian cloud needs several rollouts per dimension


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """How to fit.

    Attributes:
        optimizer: "lbfgs" (default: fewest iterations on the seed scenes) or "adam".
        iterations: most iterations per stage.
        learning_rate: Adam's step in log-parameter space.
        clip: Adam's gradient clipping (global norm).
        strategy: "direct" (whole horizon at once), "curriculum" (horizons 1/8, 1/4,
            1/2, 1 of the target), "shooting" (segments of `segment_frames` frames from
            recorded states, then the whole horizon), or "auto": direct up to
            `long_horizon_steps` steps without ground contact; beyond that, or when the
            target touches the ground, shooting when full states were recorded, else
            curriculum.
        segment_frames: frames per multiple-shooting segment.
        long_horizon_steps: targets longer than this count as long.
        tolerance: a stage stops when the loss falls below `tolerance**2` times its first value
            (converged to round-off) or, with L-BFGS, improves by less than this fraction over 5 iterations.
        step_tolerance: the last stage stops when no log-parameter moved by more than this in an iteration.
        warmup_step_tolerance: the same for the earlier (curriculum or shooting) stages, which only
            need to bring the parameters close.
        polish: finish with Levenberg-Marquardt (Gauss-Newton) steps on the whole horizon
            (at most `polish_iterations`; up to 64 parameter values). Scale-invariant, it
            finishes smooth, badly scaled valleys quickly; off by default because on
            contact-rough losses (the noisy jelly) it does not help.
        ensemble: how the full-horizon stage runs. "gradient": the optimiser on the loss.
            "ensemble": Gauss-Newton on the loss smoothed over a Gaussian cloud of parameter
            values (`ensemble_members` rollouts a step, no gradients), the cloud shrinking to
            the parameters' standard errors; it steps over the small dips that contact cuts
            into the loss, where a gradient method stops. "auto" (default): "ensemble" when
            the target touches the ground and at most `ENSEMBLE_MAX_PARAMETERS` values are
            fitted, else "gradient".
        ensemble_members: rollouts per ensemble step (even; at least 4 per fitted value).
        ensemble_spread: the cloud's initial standard deviation in log-parameter space.
    """

    optimizer: str = "lbfgs"
    iterations: int = 100
    learning_rate: float = 0.05
    clip: float = 1.0
    strategy: str = "auto"
    segment_frames: int = 10
    long_horizon_steps: int = 2000
    tolerance: float = 1e-9
    step_tolerance: float = 1e-9
    warmup_step_tolerance: float = 1e-6
    polish: bool = False
    polish_iterations: int = 20
    ensemble: str = "auto"
    ensemble_members: int = 32
    ensemble_spread: float = 0.3

    def validate(self):
        if self.optimizer not in OPTIMIZERS:
            raise InputError(
                "optimizer", f"unknown optimizer {self.optimizer!r}", f"use one of {', '.join(OPTIMIZERS)}"
            )
        if self.strategy not in STRATEGIES:
            raise InputError("strategy", f"unknown strategy {self.strategy!r}", f"use one of {', '.join(STRATEGIES)}")
        if self.ensemble not in ENSEMBLE_CHOICES:
            raise InputError(
                "ensemble", f"unknown choice {self.ensemble!r}", f"use one of {', '.join(ENSEMBLE_CHOICES)}"
            )
        if int(self.ensemble_members) < 4 or int(self.ensemble_members) % 2:
            raise InputError("ensemble_members", "must be an even number >= 4", "set e.g. ensemble_members = 32")
        for name in ("iterations", "segment_frames", "long_horizon_steps", "polish_iterations"):
            if int(getattr(self, name)) < 1:
                raise InputError(name, "must be >= 1", f"set a positive {name}")
        for name in (
            "learning_rate",
            "clip",
            "tolerance",
            "step_tolerance",
            "warmup_step_tolerance",
            "ensemble_spread",
        ):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise InputError(name, "must be a finite number > 0", f"set a positive {name}")
        return self


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of a fit over `frames` frames.

    `kind`: "direct" (the optimiser on the loss), "shooting" (segments of `frames` frames
    from recorded states) or "ensemble" (smoothed Gauss-Newton, see FitSettings.ensemble).
    """

    kind: str
    frames: int


def plan_stages(
    observations: Observations, settings: FitSettings, scene: Scene | None = None, values: int = 1
) -> list[Stage]:
    """The stages a fit of `values` scalar parameter values runs through (see FitSettings.strategy, .ensemble)."""
    total = observations.frame_count - 1
    strategy = settings.strategy
    rough = _touches_ground(scene, observations)
    if strategy == "auto":
        if observations.steps <= settings.long_horizon_steps and not rough:
            strategy = "direct"
        else:
            strategy = "shooting" if observations.full else "curriculum"
    if strategy == "shooting":
        if not observations.full:
            raise InputError(
                "strategy",
                "multiple shooting needs full recorded states of every particle",
                "use curriculum, or observe all particles",
            )
        stages = [Stage("shooting", min(settings.segment_frames, total)), Stage("direct", total)]
    elif strategy == "curriculum":
        horizons = sorted({max(2, min(total, math.ceil(total * f))) for f in (0.125, 0.25, 0.5, 1.0)})
        stages = [Stage("direct", h) for h in horizons]
    else:
        stages = [Stage("direct", total)]
    ensemble = settings.ensemble == "ensemble" or (
        settings.ensemble == "auto" and rough and values <= ENSEMBLE_MAX_PARAMETERS
    )
    if ensemble:
        if values > ENSEMBLE_MAX_PARAMETERS:
            raise InputError(
                "ensemble",
                f"the ensemble stage takes at most {ENSEMBLE_MAX_PARAMETERS} parameter values, not {values}",
                'fit scalar parameters, or set ensemble = "gradient"',
            )
        stages[-1] = Stage("ensemble", total)
    return stages


def _touches_ground(scene: Scene | None, observations: Observations) -> bool:
    """Whether the target reaches the ground plane (contact makes the loss landscape rough)."""
    if scene is None or not scene.model.has("ground"):
        return False
    return bool(np.min(observations.x[..., 1]) < float(scene.params.ground_height))


def _check_names(scene: Scene, names, init: dict | None):
    names = tuple(names)
    if not names:
        raise InputError("params", "nothing to fit", "name at least one parameter, e.g. ks")
    present = scene.params.to_dict()
    for name in names:
        if name not in FITTABLE:
            raise InputError("params", f"{name!r} cannot be fitted", f"fit some of {', '.join(FITTABLE)}")
        if name not in present:
            raise InputError(
                "params",
                f"the scene has no parameter {name!r} (its terms are {', '.join(scene.model.terms)})",
                f"fit some of {', '.join(n for n in present if n in FITTABLE)}",
            )
    for name, value in (init or {}).items():
        if name not in names:
            raise InputError(
                "init", f"{name!r} is given a start value but is not fitted", "add it to the fitted params"
            )
        value = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(value)) or np.any(value <= 0):
            raise InputError(
                f"init.{name}", f"must be > 0 (fitted in log space), got {value}", "give a positive start value"
            )
    return names


def _misfit_function(scene: Scene, observations: Observations, names, frames: int):
    """misfit(theta, data): simulated minus observed positions over the first `frames` frames, (frames, M, 3).

    theta maps name -> log value; data holds the target and its initial state.
    """
    model, base = scene.model, scene.params
    particles = jnp.asarray(observations.particles)
    every = observations.save_every

    def misfit(theta, data):
        params = base.replace(**{n: jnp.exp(theta[n]) for n in names})
        start = State(x=data["x0"], v=data["v0"])
        x = rollout(model, params, start, steps=frames * every, save_every=every).x
        return x[1:, particles] - data["x"][1 : frames + 1]

    return misfit


def _loss_function(scene: Scene, observations: Observations, names, stage: Stage):
    """loss(theta, data) for one stage; theta maps name -> log value, data holds the target."""
    model, base = scene.model, scene.params
    particles = jnp.asarray(observations.particles)
    every = observations.save_every

    def params_of(theta):
        return base.replace(**{n: jnp.exp(theta[n]) for n in names})

    if stage.kind in ("direct", "ensemble"):
        misfit = _misfit_function(scene, observations, names, stage.frames)
        return lambda theta, data: jnp.mean(misfit(theta, data) ** 2)
    segment = stage.frames

    def loss(theta, data):
        params = params_of(theta)
        count = (data["x"].shape[0] - 1) // segment
        starts = State(
            x=data["states_x"][0 : count * segment : segment], v=data["states_v"][0 : count * segment : segment]
        )
        target = data["x"][1 : count * segment + 1].reshape((count, segment) + data["x"].shape[1:])
        run = lambda s: rollout(model, params, s, steps=segment * every, save_every=every).x[1:]  # noqa: E731
        return jnp.mean((jax.vmap(run)(starts)[:, :, particles] - target) ** 2)

    return loss


def _target_data(observations: Observations) -> dict:
    data = {"x": jnp.asarray(observations.x), "x0": observations.initial_state.x, "v0": observations.initial_state.v}
    if observations.states is not None:
        data["states_x"] = jnp.asarray(observations.states.x)
        data["states_v"] = jnp.asarray(observations.states.v)
    return data


def _optimizer(settings: FitSettings):
    if settings.optimizer == "lbfgs":
        return optax.lbfgs()
    return optax.chain(optax.clip_by_global_norm(settings.clip), optax.adam(settings.learning_rate))


def _step_function(loss, settings: FitSettings, data_batched: bool):
    optimizer = _optimizer(settings)

    def single(theta, opt_state, data):
        value_fn = lambda th: loss(th, data)  # noqa: E731
        if settings.optimizer == "lbfgs":
            value, grad = optax.value_and_grad_from_state(value_fn)(theta, state=opt_state)
            updates, opt_state = optimizer.update(grad, opt_state, theta, value=value, grad=grad, value_fn=value_fn)
        else:
            value, grad = jax.value_and_grad(value_fn)(theta)
            updates, opt_state = optimizer.update(grad, opt_state, theta)
        return optax.apply_updates(theta, updates), opt_state, value

    step = jax.jit(jax.vmap(single, in_axes=(0, 0, 0 if data_batched else None)))
    init = jax.jit(jax.vmap(optimizer.init))
    value = jax.jit(jax.vmap(loss, in_axes=(0, 0 if data_batched else None)))
    return step, init, value


def _ensemble_step_function(scene: Scene, observations: Observations, names, stage: Stage, settings, batched, theta):
    """(step, init) of an ensemble stage, with the signatures of `_step_function`'s.

    Gauss-Newton on the loss smoothed over a cloud of log-parameter values u + A z (z a
    fixed symmetric set of standard normal points, A the spread). A step rolls out the
    candidate centre and its cloud in one batch; a linear fit of the cloud's residuals
    gives the smoothed residual c and Jacobian J, hence the next step
    -(J^T J + lambda diag)^-1 J^T c (Levenberg-Marquardt: a step is taken when the
    smoothed loss falls). When the steps become small against the spread (or stop
    being accepted), the spread is halved, in the shape of the parameters' standard
    errors s (J^T J)^-1/2, and the search goes on; the stage ends once the spread is
    the standard errors. Every step returns the plain loss at
    the centre, so the history shows the loss the stage minimises in the end.
    """
    members = settings.ensemble_members
    flat, unravel = ravel_pytree({n: theta[n][0] for n in names})
    size, dtype = flat.shape[0], flat.dtype
    half = np.random.default_rng(0).standard_normal((members // 2, size))
    cloud_points = jnp.asarray(np.concatenate([half, -half]), dtype=dtype)
    tiny = float(jnp.finfo(dtype).tiny)

    misfit = _misfit_function(scene, observations, names, stage.frames)

    def residuals(vector, data):
        return misfit(unravel(vector), data).reshape(-1)

    def init(theta_member):
        eye = jnp.eye(size, dtype=dtype)
        zero = jnp.zeros((), dtype)
        return {
            "spread": settings.ensemble_spread * eye,
            "damping": jnp.asarray(1e-3, dtype),
            "fresh": zero + 1,  # the next step evaluates the centre with a new spread
            "done": zero,
            "smoothed": zero + jnp.inf,
            "loss": zero + jnp.inf,
            "sigma2": zero,
            "gradient": jnp.zeros(size, dtype),
            "normal": eye,
        }

    def single(theta_member, state, data):
        centre = ravel_pytree({n: theta_member[n] for n in names})[0]
        fresh = state["fresh"] > 0
        normal = state["normal"]
        step = -jnp.linalg.solve(normal + state["damping"] * jnp.diag(jnp.diag(normal)), state["gradient"])
        step = jnp.where(fresh | ~jnp.all(jnp.isfinite(step)), 0.0, step)
        candidate = centre + step
        cloud = candidate + cloud_points @ state["spread"].T
        r = jax.vmap(residuals, in_axes=(0, None))(jnp.concatenate([candidate[None], cloud]), data)
        r_centre, r = r[0], r[1:]
        count = r_centre.shape[0]
        finite = jnp.all(jnp.isfinite(r), axis=1)
        weight = finite.astype(dtype)
        used = jnp.maximum(weight.sum(), 1.0)
        r = jnp.where(finite[:, None], r, 0.0)
        mean = weight @ r / used
        smoothed = weight @ jnp.sum(r**2, axis=1) / (used * count)
        usable = (weight.sum() >= 0.75 * members) & jnp.all(jnp.isfinite(r_centre))
        smoothed = jnp.where(usable, smoothed, jnp.inf)
        offsets = (cloud - weight @ cloud / used) * weight[:, None]
        slopes = jnp.linalg.solve(offsets.T @ offsets, offsets.T @ ((r - mean) * weight[:, None]))  # J^T, (P, n)
        accept = usable & (fresh | (smoothed < state["smoothed"]))
        chosen = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        normal = chosen(slopes @ slopes.T, normal)
        sigma2 = chosen(r_centre @ r_centre / max(count - size, 1), state["sigma2"])
        new = {
            "gradient": chosen(slopes @ mean, state["gradient"]),
            "normal": normal,
            "sigma2": sigma2,
            "smoothed": chosen(smoothed, state["smoothed"]),
            "loss": chosen(r_centre @ r_centre / count, state["loss"]),
        }
        damping = jnp.where(accept, jnp.maximum(state["damping"] / 10, 1e-6), state["damping"] * 10)
        relative = jnp.linalg.norm(jnp.linalg.solve(state["spread"], step))  # the step in units of the spread
        level_end = ~fresh & ((relative <= 0.1) | (~accept & (damping >= 1e3)))  # small steps left, or none
        # The standard errors' square root s (J^T J)^-1/2 and the spread's axes measured in it.
        # A level halves the spread (in the standard errors' shape) until it is the standard
        # errors; where the cloud's residuals are linear in the parameters to 1% (the loss is
        # smooth at this scale: no dips to step over) it goes straight there. The spread never
        # exceeds its start; the stage ends when it is within 10% of the standard errors or
        # cannot shrink further (a parameter the data barely determine).
        eigenvalues, vectors = jnp.linalg.eigh(normal)
        eigenvalues = jnp.maximum(eigenvalues, 1e-12 * eigenvalues.max() + tiny)
        noise = jnp.sqrt(jnp.maximum(sigma2, tiny))
        posterior = (vectors * (noise / jnp.sqrt(eigenvalues))) @ vectors.T
        whiten = (vectors * (jnp.sqrt(eigenvalues) / noise)) @ vectors.T
        sizes = jnp.linalg.svd(whiten @ state["spread"], compute_uv=False)
        fitted = offsets @ slopes
        nonlinear = jnp.sum(((r - mean) * weight[:, None] - fitted) ** 2) / jnp.maximum(jnp.sum(fitted**2), tiny)
        shrunk = posterior * jnp.where(nonlinear < 1e-2, 1.0, jnp.maximum(1.0, sizes.min() / 2))
        shrunk = shrunk * jnp.minimum(1.0, settings.ensemble_spread / jnp.linalg.norm(shrunk, 2))
        stalled = jnp.linalg.norm(shrunk, 2) >= 0.9 * jnp.linalg.norm(state["spread"], 2)
        finished = level_end & ((sizes.max() <= 1.1) | stalled)
        failed_start = fresh & ~usable  # the cloud reaches unstable values: halve it and evaluate again
        spread = jnp.where(level_end & ~finished, shrunk, state["spread"])
        spread = jnp.where(failed_start, spread / 2, spread)
        new.update(
            spread=spread,
            damping=jnp.where(level_end, jnp.asarray(1e-3, dtype), damping),
            fresh=(level_end & ~finished) | failed_start,
            done=finished | (state["done"] > 0),
        )
        new = {k: jnp.asarray(v, dtype) for k, v in new.items()}
        value = jnp.where(fresh, new["loss"], state["loss"])
        moved = unravel(candidate)
        theta_new = {n: jnp.where(accept & (state["done"] == 0), moved[n], theta_member[n]) for n in names}
        return theta_new, new, value

    step = jax.jit(jax.vmap(single, in_axes=(0, 0, 0 if batched else None)))
    return step, jax.jit(jax.vmap(init))


@dataclasses.dataclass
class FitProgress:
    """Everything needed to continue a fit exactly where it stopped (saved in fit files).

    Attributes:
        stage: index of the current stage.
        iteration: iterations done in the current stage.
        theta: log parameter values, name -> (B, ...).
        optimizer_leaves: the optimizer state's arrays (its structure is rebuilt from the settings).
        loss: loss before each completed iteration, list of (B,) arrays.
        values: parameter values before each completed iteration, name -> list of (B, ...) arrays.
        stage_of_iteration: stage index of each completed iteration.
        last_step: largest log-parameter change of the last iteration, per member (B,).
        done: whether the fit finished.
        wall_s: time spent so far [s].
    """

    stage: int
    iteration: int
    theta: dict
    optimizer_leaves: list | None
    loss: list
    values: dict
    stage_of_iteration: list
    last_step: np.ndarray | None = None
    done: bool = False
    wall_s: float = 0.0


@dataclasses.dataclass(frozen=True)
class Identifiability:
    """Gauss-Newton uncertainty at the optimum.

    Attributes:
        standard_error: name -> standard error of the parameter (same units).
        relative_standard_error: name -> standard error / value.
        correlation: (P, P) correlation matrix of the (log) parameters, in `names` order.
        names: parameter names of the correlation matrix's rows.
        noise_std: residual standard deviation [m] used for the estimate.
        warnings: plain-language warnings (not identifiable, poorly determined, confounded).
    """

    standard_error: dict
    relative_standard_error: dict
    correlation: np.ndarray
    names: tuple
    noise_std: float
    warnings: tuple


@dataclasses.dataclass(frozen=True)
class FitResult:
    """The outcome of a fit (one member; `fit_batch` returns a list of these).

    Attributes:
        names: fitted parameter names.
        initial, final: name -> value at the start and at the end.
        loss_history: loss [m^2] before each iteration, then the final loss, shape (iterations + 1,).
        value_history: name -> value before each iteration, then the final value.
        stages: the stages run; stage_of_iteration says which stage each iteration belongs to.
        iterations: iterations run in all.
        wall_s: wall time [s].
        identifiability: Gauss-Newton standard errors and correlations (None if skipped).
        truth: true values when known (synthetic targets).
    """

    names: tuple
    initial: dict
    final: dict
    loss_history: np.ndarray
    value_history: dict
    stages: tuple
    stage_of_iteration: np.ndarray
    iterations: int
    wall_s: float
    identifiability: Identifiability | None
    truth: dict | None = None

    @property
    def final_loss(self) -> float:
        return float(self.loss_history[-1])

    def relative_errors(self) -> dict:
        """name -> |final - true| / |true| (max over items for per-item parameters), when the truth is known."""
        if not self.truth:
            return {}
        return {
            n: float(np.max(np.abs(np.asarray(self.final[n]) - self.truth[n]) / np.abs(self.truth[n])))
            for n in self.names
            if n in self.truth
        }

    def table(self) -> str:
        """A plain-text table: fitted value, true value, relative error, standard error."""
        ident = self.identifiability
        rows = [f"{'param':<7}{'initial':>12}{'fitted':>14}{'true':>12}{'rel. error':>12}{'std. error':>12}"]
        errors = self.relative_errors()
        for n in self.names:
            value = np.asarray(self.final[n])
            true = "" if not self.truth or n not in self.truth else _short(self.truth[n])
            rel = f"{errors[n]:.2e}" if n in errors else ""
            se = _short(ident.standard_error[n]) if ident else ""
            rows.append(f"{n:<7}{_short(self.initial[n]):>12}{_short(value):>14}{true:>12}{rel:>12}{se:>12}")
        rows.append(f"final loss {self.final_loss:.4g} m^2 after {self.iterations} iterations in {self.wall_s:.2f} s")
        if ident:
            rows += [f"warning: {w}" for w in ident.warnings]
        return "\n".join(rows)


def _short(value) -> str:
    value = np.asarray(value)
    if value.ndim == 0:
        return f"{float(value):.6g}"
    return f"mean {float(value.mean()):.4g}"


def fit(
    scene: Scene,
    observations: Observations,
    params=("ks", "kd"),
    init: dict | None = None,
    settings: FitSettings | None = None,
    **kwargs,
) -> FitResult:
    """Fit `params` of `scene` to `observations` by gradient-based optimisation through rollouts.

    Args:
        scene: the model and its other parameters (held fixed).
        observations: the target (see `observations_from_trajectory`, `synthetic_observations`).
        params: names to fit, e.g. ("ks", "kd", "cd").
        init: start values (name -> positive value); default: the scene's values.
        settings: a FitSettings; keyword arguments override its fields.
    Returns:
        FitResult with the fitted values, histories and the identifiability report.

    Example:
        >>> obs = js.synthetic_observations(scene, {"ks": 1000.0, "kd": 5.0, "cd": 0.05}, 1000, 10)
        >>> result = js.fit(scene, obs, ["ks", "kd", "cd"], init={"ks": 400.0, "kd": 12.0, "cd": 0.15})
        >>> print(result.table())
    """
    return fit_batch(scene, [observations], params, [init or {}], settings, **kwargs)[0]


def fit_batch(
    scene: Scene,
    observations: list[Observations],
    params=("ks", "kd"),
    inits: list[dict] | None = None,
    settings: FitSettings | None = None,
    progress: FitProgress | None = None,
    on_iteration: Callable[[FitProgress, list[Stage]], None] | None = None,
    identify: bool = True,
    **kwargs,
) -> list[FitResult]:
    """Fit several starting guesses (multi-start) and/or several targets at once with `vmap`.

    `observations` holds one target (shared by all members) or one per member;
    `inits` one start per member (default: one member starting at the scene's values).
    `progress` continues an interrupted fit; `on_iteration(progress, stages)` is called
    after every iteration (the CLI checkpoints from it). With several devices and a
    member count divisible by their number, the members are split across them
    (`shard_batch`); the numbers are the same as on one device.

    Example:
        >>> results = js.fit_batch(scene, [obs], ["ks", "kd"], inits=[{"ks": 300.0}, {"ks": 3000.0}])
        >>> [r.final["ks"] for r in results]
    """
    settings = dataclasses.replace(settings or FitSettings(), **kwargs).validate()
    inits = list(inits) if inits else [{}]
    if len(observations) not in (1, len(inits)):
        if len(inits) == 1:
            inits = inits * len(observations)
        else:
            raise InputError(
                "observations",
                f"{len(observations)} targets for {len(inits)} starts",
                "give one target or one per start",
            )
    names = tuple(params)
    for init in inits:
        _check_names(scene, names, init)
    members = len(inits)
    shapes = [o.x.shape for o in observations]
    if len(set(shapes)) != 1:
        raise InputError(
            "observations", f"targets differ in shape {shapes}", "give targets of equal length and particles"
        )
    reference = observations[0]
    batched_data = len(observations) > 1
    if batched_data:
        data = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[_target_data(o) for o in observations])
    else:
        data = _target_data(reference)
    present = scene.params.to_dict()
    stages = plan_stages(reference, settings, scene, values=sum(int(np.size(present[n])) for n in names))
    start_values = [{n: jnp.asarray(init.get(n, present[n]), dtype=float) for n in names} for init in inits]
    if progress is None:
        theta = {n: jnp.stack([jnp.log(jnp.broadcast_to(s[n], present[n].shape)) for s in start_values]) for n in names}
        progress = FitProgress(0, 0, theta, None, [], {n: [] for n in names}, [])
    if jax.device_count() > 1 and members % jax.device_count() == 0:  # members across devices
        progress.theta = shard_batch(progress.theta)
        if batched_data:
            data = shard_batch(data)
    start_clock = time.perf_counter() - progress.wall_s
    while not progress.done:
        stage = stages[progress.stage]
        if stage.kind == "ensemble":
            step, init_opt = _ensemble_step_function(
                scene, reference, names, stage, settings, batched_data, progress.theta
            )
        else:
            step, init_opt, _ = _step_function(_loss_function(scene, reference, names, stage), settings, batched_data)
        opt_state = init_opt(progress.theta)
        if progress.optimizer_leaves is not None:
            structure = jax.tree_util.tree_structure(opt_state)
            opt_state = jax.tree_util.tree_unflatten(structure, [jnp.asarray(a) for a in progress.optimizer_leaves])
        final_stage = progress.stage == len(stages) - 1
        while progress.iteration < settings.iterations and not _converged(progress, settings, final_stage, opt_state):
            values = {n: np.asarray(jnp.exp(progress.theta[n])) for n in names}
            theta, opt_state, value = step(progress.theta, opt_state, data)
            progress.last_step = np.max(
                np.stack(
                    [np.abs(np.asarray(theta[n] - progress.theta[n])).reshape(members, -1).max(axis=1) for n in names]
                ),
                axis=0,
            )
            progress.theta = theta
            progress.loss.append(np.asarray(value))
            for n in names:
                progress.values[n].append(values[n])
            progress.stage_of_iteration.append(progress.stage)
            progress.iteration += 1
            progress.optimizer_leaves = [np.asarray(a) for a in jax.tree_util.tree_leaves(opt_state)]
            progress.wall_s = time.perf_counter() - start_clock
            if on_iteration:
                on_iteration(progress, stages)
        progress.stage += 1
        progress.iteration = 0
        progress.optimizer_leaves = None
        progress.last_step = None
        progress.done = progress.stage >= len(stages)
        progress.wall_s = time.perf_counter() - start_clock
        if on_iteration:
            on_iteration(progress, stages)
    return _results(scene, observations, names, start_values, settings, stages, progress, data, identify)


def _converged(progress: FitProgress, settings: FitSettings, final_stage: bool, opt_state) -> bool:
    """Whether every member has converged in the current stage (see FitSettings)."""
    if isinstance(opt_state, dict) and "done" in opt_state:  # an ensemble stage says so itself
        return bool(np.all(np.asarray(opt_state["done"]) > 0))
    if progress.last_step is not None:
        limit = settings.step_tolerance if final_stage else settings.warmup_step_tolerance
        if np.all(progress.last_step <= limit):
            return True
    in_stage = [loss for loss, s in zip(progress.loss, progress.stage_of_iteration) if s == progress.stage]
    if len(in_stage) < 2:
        return False
    first, now = np.asarray(in_stage[0]), np.asarray(in_stage[-1])
    if np.all(now <= settings.tolerance**2 * first):
        return True
    if len(in_stage) < 6 or settings.optimizer != "lbfgs":  # Adam's loss is not monotone
        return False
    before = np.asarray(in_stage[-6])
    return bool(np.all((before - now) <= settings.tolerance * np.abs(before)))


def _results(scene, observations, names, start_values, settings, stages, progress, data, identify):
    batched_data = len(observations) > 1
    loss = _loss_function(scene, observations[0], names, stages[-1])
    _, _, value = _step_function(loss, settings, batched_data)
    final_loss = np.asarray(value(progress.theta, data))
    results = []
    polish_stage = Stage("gauss_newton", observations[0].frame_count - 1)
    for member, start in enumerate(start_values):
        obs = observations[member if batched_data else 0]
        final = {n: np.asarray(jnp.exp(progress.theta[n][member])) for n in names}
        history = [np.asarray(loss)[member] for loss in progress.loss]
        value_history = {n: [v[member] for v in progress.values[n]] for n in names}
        stage_of_iteration = list(progress.stage_of_iteration)
        polish_start = time.perf_counter()
        steps = _gauss_newton_polish(scene, obs, names, final, settings) if settings.polish else []
        for loss_before, values_before in steps:
            history.append(loss_before)
            for n in names:
                value_history[n].append(values_before[n])
            stage_of_iteration.append(len(stages))
        if steps:
            final = steps.final
            final_loss_member = steps.final_loss
        else:
            final_loss_member = final_loss[member]
        ident = identifiability(scene, obs, names, final) if identify else None
        results.append(
            FitResult(
                names=names,
                initial={n: np.asarray(start[n]) for n in names},
                final=final,
                loss_history=np.array(history + [final_loss_member]),
                value_history={n: np.array(value_history[n] + [final[n]]) for n in names},
                stages=tuple(stages) + ((polish_stage,) if steps else ()),
                stage_of_iteration=np.asarray(stage_of_iteration, dtype=int),
                iterations=len(history),
                wall_s=progress.wall_s + time.perf_counter() - polish_start,
                identifiability=ident,
                truth={n: obs.truth[n] for n in names if n in obs.truth} if obs.truth else None,
            )
        )
    return results


def _residual_function(scene: Scene, observations: Observations, names, values: dict):
    """(flat log parameters, unravel, residuals(flat) -> (n,)) for the full horizon."""
    theta = {n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names}
    flat, unravel = ravel_pytree(theta)
    base, model = scene.params, scene.model.forward_mode()  # Jacobians are taken with jacfwd
    particles = jnp.asarray(observations.particles)
    every, frames = observations.save_every, observations.frame_count - 1
    target = jnp.asarray(observations.x)

    def residuals(vector):
        p = base.replace(**{n: jnp.exp(v) for n, v in unravel(vector).items()})
        x = rollout(model, p, observations.initial_state, steps=frames * every, save_every=every).x
        return (x[1:, particles] - target[1:]).reshape(-1)

    return flat, unravel, residuals


class _PolishSteps(list):
    """(loss, values) before each accepted Gauss-Newton step, plus the final values and loss."""

    final: dict
    final_loss: float


def _gauss_newton_polish(scene, observations, names, values, settings, max_parameters: int = 64):
    """Levenberg-Marquardt on the full-horizon residuals, from the first-order optimiser's answer.

    Least squares with few parameters is what Gauss-Newton is for: it is invariant to the
    parameters' scales, so it finishes a flat, badly scaled valley (the jelly's damping
    against its stiffness) where a first-order method crawls.
    """
    flat, unravel, residuals = _residual_function(scene, observations, names, values)
    if flat.shape[0] > max_parameters:
        return []
    residuals = jax.jit(residuals)
    jacobian = jax.jit(jax.jacfwd(residuals))
    flat = np.asarray(flat)
    r = np.asarray(residuals(flat))
    cost = float(r @ r)
    steps = _PolishSteps()
    damping = 1e-3
    to_values = lambda v: {n: np.asarray(jnp.exp(x)) for n, x in unravel(jnp.asarray(v)).items()}  # noqa: E731
    for _ in range(settings.polish_iterations):
        jac = np.asarray(jacobian(flat))
        gradient, normal = jac.T @ r, jac.T @ jac
        scale = np.maximum(np.diag(normal), 1e-300)
        accepted = False
        for _ in range(12):
            step = -np.linalg.pinv(normal + damping * np.diag(scale), rcond=1e-14) @ gradient
            candidate = flat + step
            r_new = np.asarray(residuals(candidate))
            cost_new = float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                accepted = True
                break
            damping *= 10.0
        if not accepted:
            break
        steps.append((cost / r.size, to_values(flat)))
        improvement = (cost - cost_new) / cost
        flat, r, cost = candidate, r_new, cost_new
        damping = max(damping / 10.0, 1e-12)
        if np.max(np.abs(step)) <= settings.step_tolerance or improvement <= settings.tolerance**2:
            break
    steps.final = to_values(flat)
    steps.final_loss = cost / r.size
    return steps


def identifiability(scene: Scene, observations: Observations, names, values: dict, max_parameters: int = 64):
    """Gauss-Newton standard errors and correlations of `values` for the full-horizon fit.

    With residuals r (observed minus simulated positions) and J = dr/d(log p), the
    covariance of log p is s^2 (J^T J)^-1 with s^2 = |r|^2 / (n - P); a parameter's
    standard error is its value times its log standard error. Warns when the data do
    not depend on a parameter, when it is poorly determined (relative standard error
    above 50%), when two parameters are confounded (|correlation| > 0.95), and when the
    loss one standard error away disagrees with the quadratic model (a rough loss).

    Example:
        >>> report = js.identifiability(scene, obs, ["ks", "kd"], result.final)
    """
    names = tuple(names)
    flat, unravel, residuals = _residual_function(scene, observations, names, values)
    theta = unravel(flat)
    if flat.shape[0] > max_parameters:
        return None
    r = np.asarray(residuals(flat))
    jac = np.asarray(jax.jit(jax.jacfwd(residuals))(flat))
    count, dims = r.shape[0], flat.shape[0]
    sigma2 = float(r @ r) / max(count - dims, 1)
    labels = _labels(theta)
    warnings = []
    column = np.linalg.norm(jac, axis=0)
    dead = column <= 1e-10 * max(float(column.max()), 1e-300)
    for i in np.nonzero(dead)[0]:
        warnings.append(f"{labels[i]} is not identifiable: the observed motion does not depend on it")
    # invert on unit-norm columns (so a parameter with a tiny effect is not cut off by a
    # round-off threshold), then undo the scaling; directions the data cannot see get
    # infinite variance rather than zero
    scale = np.where(dead, 1.0, column)
    scaled = jac / scale
    eigenvalues, eigenvectors = np.linalg.eigh(scaled.T @ scaled)
    visible = eigenvalues > 1e-13 * max(float(eigenvalues.max()), 1e-300)
    inverse = (eigenvectors[:, visible] / eigenvalues[visible]) @ eigenvectors[:, visible].T
    covariance = sigma2 * inverse / np.outer(scale, scale)
    log_se = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    blind = np.abs(eigenvectors[:, ~visible]).max(axis=1) > 1e-3 if (~visible).any() else np.zeros(dims, bool)
    log_se[dead | blind] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.outer(log_se, log_se)
    correlation[~np.isfinite(correlation)] = 0.0
    np.fill_diagonal(correlation, 1.0)
    se_tree = unravel(jnp.asarray(log_se))
    standard_error = {n: np.asarray(values[n]) * np.asarray(se_tree[n]) for n in names}
    relative = {n: np.asarray(se_tree[n]) for n in names}  # d(log p) = dp / p
    for i, label in enumerate(labels):
        if not dead[i] and log_se[i] > 0.5:
            warnings.append(f"{label} is poorly determined: standard error {100 * log_se[i]:.0f}% of its value")
    warnings += _roughness_warnings(jax.jit(residuals), flat, r, jac, log_se, labels)
    for i in range(dims):
        for j in range(i + 1, dims):
            if abs(correlation[i, j]) > 0.95 and not (dead[i] or dead[j]):
                warnings.append(
                    f"{labels[i]} and {labels[j]} are confounded (correlation {correlation[i, j]:+.3f}): "
                    "the data constrain a combination of them, not each"
                )
    return Identifiability(standard_error, relative, correlation, tuple(labels), math.sqrt(sigma2), tuple(warnings))


def _roughness_warnings(residuals, flat, r, jac, log_se, labels) -> list[str]:
    """Check the Gauss-Newton quadratic model one standard error either side of the point.

    Moving log p_i by d = +-s_i changes the sum of squares, to second order, by
    2 (J^T r)_i d + (d |J_i|)^2. When the actual change misses that by more than half the
    curvature term, the loss is not smooth there (contact switching on at discrete steps
    does this): the standard errors are then not to be trusted and the fit may sit in a
    local dip.
    """
    warnings = []
    cost = float(r @ r)
    slope = jac.T @ r
    for i, label in enumerate(labels):
        if not (1e-6 < log_se[i] < 1.0):  # determined to round-off, or already flagged as poorly determined
            continue
        curvature = float((log_se[i] * np.linalg.norm(jac[:, i])) ** 2)
        for sign in (1.0, -1.0):
            step = sign * log_se[i]
            moved = np.array(flat, dtype=float)
            moved[i] += step
            change = float(np.sum(np.asarray(residuals(jnp.asarray(moved))) ** 2)) - cost
            predicted = 2.0 * float(slope[i]) * step + curvature
            if abs(change - predicted) > 0.5 * curvature:
                warnings.append(
                    f"{label}: the loss is not smooth near the fit (one standard error away it changes by "
                    f"{change / curvature:.2g} where the quadratic model predicts {predicted / curvature:.2g}, "
                    "in units of the curvature term); its standard error is unreliable and a gradient fit may stop in a local dip"
                )
                break
    return warnings


def _labels(theta: dict) -> list[str]:
    labels = []
    for name, value in sorted(theta.items()):
        size = int(np.size(value))
        labels += [name] if np.ndim(value) == 0 else [f"{name}[{i}]" for i in range(size)]
    return labels
