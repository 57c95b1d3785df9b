"""Stable time-step estimates and blow-up detection."""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .integrators import INTEGRATORS, as_integrator
from .model import Model
from .params import Params
from .rollout import energy, simulate, term_energies
from .state import State, Trajectory

ENERGY_GAIN_FACTOR = 0.5  # energy may not grow by more than this fraction of the energy scale


@dataclasses.dataclass(frozen=True)
class StabilityEstimate:
    """Linearised-stability numbers for a scene at a state.

    Attributes:
        omega_max: largest angular frequency of the linearised system [rad/s].
        damping_max: largest damping rate c of the linearised system [1/s].
        dt_bound: largest stable dt of the scene's integrator [s] (inf: unconditionally stable).
        dt: the model's dt [s].
        integrator: the scene's integrator.
        bounds: largest stable dt of every integrator [s], name -> bound.

    The bounds are those of the test equation x'' = -omega_max^2 x - damping_max x'
    stepped by the integrators' own code: the largest dt at which the step's
    amplification matrix has spectral radius <= 1 (semi-implicit Euler: the root of
    (omega dt)^2 + 2 c dt = 4, i.e. 2 / omega_max without damping).
    """

    omega_max: float
    damping_max: float
    dt_bound: float
    dt: float
    integrator: str = "semi_implicit_euler"
    bounds: dict = dataclasses.field(default_factory=dict)

    @property
    def margin(self) -> float:
        """dt_bound / dt: above 1 is stable, below 1 blows up."""
        return self.dt_bound / self.dt

    def describe(self) -> str:
        bound = "unconditionally stable" if math.isinf(self.dt_bound) else f"stable dt <= {self.dt_bound:.4g} s"
        return (
            f"omega_max {self.omega_max:.4g} rad/s, damping {self.damping_max:.4g} 1/s: {self.integrator} {bound}, "
            f"scene dt {self.dt:.4g} s, margin {self.margin:.3g}x"
        )

    def table(self) -> str:
        """One line per integrator: order, stable dt, margin at the scene's dt."""
        lines = [f"{'integrator':<20} {'order':>5} {'stable dt [s]':>14} {'margin':>9}"]
        for name, bound in self.bounds.items():
            text = "unconditional" if math.isinf(bound) else f"{bound:.4g}"
            margin = "inf" if math.isinf(bound) else f"{bound / self.dt:.3g}x"
            mark = "  <- scene" if name == self.integrator else ""
            lines.append(f"{name:<20} {INTEGRATORS[name].order:>5} {text:>14} {margin:>9}{mark}")
        return "\n".join(lines)


def estimate_stability(model: Model, params: Params, state: State, iterations: int = 100) -> StabilityEstimate:
    """Estimate omega_max, the damping rate and every integrator's stable dt.

    Linearises the force at `state` (springs, ground contact assumed for every
    particle when the scene has a ground, since a falling body will touch it)
    and runs power iteration on M^-1/2 K M^-1/2 and M^-1/2 C M^-1/2, where
    K = -dF/dx and C = -dF/dv, restricted to free particles. The stable dt of each
    integrator is then found on the test equation with those two rates
    (`stable_dt`).

    Example:
        >>> js.sim.estimate_stability(scene.model, scene.params, scene.state).dt_bound
    """
    # the force reads neither dt nor the integrator: one compiled iteration serves every choice
    linear = model.forward_mode().replace(backend="jax", dt=1.0, integrator="semi_implicit_euler")
    omega_sq, damping = _power_iterations(linear, params, state, iterations)
    omega_sq, damping = float(omega_sq), float(damping)
    if model.has("ground"):
        scale = 1.0 / np.asarray(model.mass)
        omega_sq += float(np.max(np.asarray(params.kg) * scale))
        damping += float(np.max(np.asarray(params.kgd) * scale))
    omega, damping = math.sqrt(max(omega_sq, 0.0)), max(damping, 0.0)
    bounds = {name: stable_dt(name, omega, damping) for name in INTEGRATORS}
    name = model.integrator.name
    return StabilityEstimate(omega, damping, bounds[name], model.dt, name, bounds)


@functools.cache
def _amplification(integrator):
    """The step's 2 x 2 amplification matrix on x'' = -w^2 x - c x', as a function of (w, c, dt)."""
    step = integrator.step
    one = jnp.ones((1, 1))

    def advance(y, omega, damping, dt):
        x, v = step(lambda x, v: -(omega**2) * x - damping * v, one, jnp.ones((1, 1), bool), y[0] * one, y[1] * one, dt)
        return jnp.stack([x[0, 0], v[0, 0]])

    return jax.jit(jax.jacfwd(advance))


def stable_dt(integrator, omega: float, damping: float = 0.0) -> float:
    """Largest dt at which `integrator` is stable on x'' = -omega^2 x - damping x' [s].

    Bisection on the spectral radius of the integrator's own amplification matrix
    (evaluated through its code); inf when it is stable at every dt tried (up to
    1e6 / rate), as backward Euler is.

    Example:
        >>> js.sim.stable_dt("semi_implicit_euler", omega=100.0)   # 2 / 100
        0.02
    """
    rate = max(omega, damping)
    if rate <= 0:
        return math.inf
    matrix = _amplification(as_integrator(integrator))
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    y0 = jnp.zeros(2, dtype)

    def stable(dt):
        a = np.asarray(matrix(y0, jnp.asarray(omega, dtype), jnp.asarray(damping, dtype), jnp.asarray(dt, dtype)))
        return bool(np.all(np.isfinite(a))) and float(np.max(np.abs(np.linalg.eigvals(a)))) <= 1.0 + 1e-6

    low, high = 0.0, 0.1 / rate
    while stable(high):
        low, high = high, 2.0 * high
        if high > 1e6 / rate:
            return math.inf
    for _ in range(40):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if stable(middle) else (low, middle)
    return low


@functools.partial(jax.jit, static_argnames=("iterations",))
def _power_iterations(model, params, state, iterations):
    free = (~model.pinned)[:, None]
    root_inv_mass = (1.0 / jnp.sqrt(model.mass))[:, None]
    # Without the ground term: contact is added as a bound by the caller.
    linear_model = model.replace(terms=tuple(t for t in model.terms if t != "ground"))

    def operator(wrt):
        def apply(q):
            q = q * root_inv_mass * free
            if wrt == "x":
                _, dforce = jax.jvp(lambda x: linear_model.force(params, x, state.v), (state.x,), (q,))
            else:
                _, dforce = jax.jvp(lambda v: linear_model.force(params, state.x, v), (state.v,), (q,))
            return -dforce * root_inv_mass * free

        return apply

    def largest(apply):
        q0 = jax.random.normal(jax.random.PRNGKey(0), state.x.shape, state.x.dtype) * free
        q0 = q0 / jnp.maximum(jnp.linalg.norm(q0), 1e-30)

        def body(_, q):
            w = apply(q)
            w = w / jnp.maximum(jnp.max(jnp.abs(w)), 1e-300)  # first to O(1): |w|^2 would overflow at 1e154
            return w / jnp.maximum(jnp.linalg.norm(w), 1e-30)

        q = jax.lax.fori_loop(0, iterations, body, q0)
        return jnp.abs(jnp.vdot(q, apply(q)))

    return largest(operator("x")), largest(operator("v"))


@dataclasses.dataclass(frozen=True)
class BlowUp:
    """Where a rollout went wrong.

    Attributes:
        step: index of the first bad time step (1-based count of steps taken).
        time: simulated time at that step [s].
        reason: "non-finite state" or "energy exploded".
        stability: the scene's stable-dt estimate.
    """

    step: int
    time: float
    reason: str
    stability: StabilityEstimate

    def describe(self) -> str:
        s = self.stability
        if math.isinf(s.dt_bound) or s.margin >= 1:
            advice = f"the linearised estimate ({s.describe()}) did not predict this; reduce dt or check the scene"
        else:
            advice = (
                f"reduce dt below {s.dt_bound:.3g} s ({s.integrator}'s stable-dt estimate, "
                f"omega_max {s.omega_max:.4g} rad/s), or use backward_euler"
            )
        return f"simulation blew up at step {self.step} (t = {self.time:.6g} s): {self.reason}; {advice}"


def energy_threshold(model: Model, params: Params, state: State) -> float:
    """Energy above which a rollout starting at `state` counts as exploded [J].

    Without energy sources the total energy never exceeds its start; we allow
    ENERGY_GAIN_FACTOR times a generous scale (kinetic + potential magnitudes
    plus the weight times the size of the scene) for integration error.
    """
    e0 = float(energy(model, params, state))
    x = np.asarray(state.x)
    size = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0))) + 1.0
    scale = 1.0 + abs(e0) + 0.5 * float(np.sum(np.asarray(model.mass)[:, None] * np.asarray(state.v) ** 2))
    for term_energy in term_energies(model, params, state.x):
        scale += abs(float(term_energy))
    if model.has("gravity"):
        scale += float(np.sum(np.asarray(model.mass)) * np.linalg.norm(np.asarray(params.gravity))) * size
    return e0 + ENERGY_GAIN_FACTOR * scale


def first_bad_frame(model: Model, params: Params, x, v, threshold: float) -> int | None:
    """Index of the first frame in x, v (frames, N, 3) that is non-finite or above `threshold` J."""
    frames = Trajectory(x=jnp.asarray(x), v=jnp.asarray(v), t=jnp.zeros(x.shape[0]))
    e = np.asarray(energy(model, params, frames))
    finite = np.isfinite(np.asarray(x)).all(axis=(1, 2)) & np.isfinite(np.asarray(v)).all(axis=(1, 2))
    bad = ~finite | ~np.isfinite(e) | (e > threshold)
    return int(np.argmax(bad)) if bad.any() else None


def locate_blowup(
    model: Model,
    params: Params,
    good_state: State,
    good_step: int,
    max_steps: int,
    threshold: float,
    stability: StabilityEstimate,
    chunk: int = 2000,
) -> BlowUp:
    """Re-run step by step from `good_state` (at step `good_step`) for up to `max_steps` steps,
    in chunks, to find the exact first bad step. Callers start from the initial state, so the
    step found does not depend on which frames were saved: energy can exceed the threshold
    between saved frames and fall back below it (contact) before the run diverges."""
    state, step, remaining = good_state, good_step, int(max_steps)
    while remaining > 0:
        count = min(chunk, remaining)
        end, x, v = simulate(model, params, state, count, 1)
        offset = first_bad_frame(model, params, x, v, threshold)
        if offset is not None:
            xs, vs = np.asarray(x[offset]), np.asarray(v[offset])
            finite = np.isfinite(xs).all() and np.isfinite(vs).all()
            reason = "energy exploded" if finite else "non-finite state"
            first = step + offset + 1
            return BlowUp(step=first, time=first * model.dt, reason=reason, stability=stability)
        state, step, remaining = end, step + count, remaining - count
    return BlowUp(step=step, time=step * model.dt, reason="energy exploded", stability=stability)


def find_blowup(model: Model, params: Params, trajectory: Trajectory) -> BlowUp | None:
    """Check a finished rollout; return where it blew up, or None if it stayed sane.

    The rollout itself carries no checks (the fast path stays fast); this looks
    at the saved frames afterwards and re-simulates the one bad interval step by
    step to report the exact step index.

    Example:
        >>> traj = js.rollout(model, params, state, steps=5000, save_every=50)
        >>> problem = js.sim.find_blowup(model, params, traj)
        >>> if problem: print(problem.describe())
    """
    first = trajectory.frame(0)
    threshold = energy_threshold(model, params, first)
    bad = first_bad_frame(model, params, trajectory.x, trajectory.v, threshold)
    if bad is None:
        return None
    save_every = trajectory.stride(model.dt)
    stability = estimate_stability(model, params, first)
    if bad == 0:
        return BlowUp(0, 0.0, "non-finite initial state", stability)
    return locate_blowup(model, params, first, 0, bad * save_every, threshold, stability)
