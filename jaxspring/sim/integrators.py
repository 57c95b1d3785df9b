"""Time integrators.

Each integrator is a pure function `(force, mass, free, x, v, dt) -> (x', v')`:
`force(x, v)` is the total force (N, 3), `mass` the masses as a column (N, 1),
`free` a boolean column (N, 1) that is False for pinned particles (they keep x
and have v = 0). Written against a force function rather than a model, the same
code steps a scene and the scalar test equation x'' = -omega^2 x - c x' that the
stability analyser uses, so the dt bounds it prints are those of this code.

| name                | order | force evaluations / step | stable dt (undamped)       |
|---------------------|-------|--------------------------|----------------------------|
| semi_implicit_euler | 1     | 1                        | 2 / omega_max              |
| verlet              | 2     | 2                        | 2 / omega_max              |
| rk4                 | 4     | 4                        | 2.83 / omega_max           |
| backward_euler      | 1     | Newton + CG              | unconditional (A-stable)   |
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax.scipy.sparse.linalg import cg, gmres

from ..sim.state import State


def _acceleration(force, mass, free):
    return lambda x, v: jnp.where(free, force(x, v) / mass, 0.0)


def semi_implicit_euler(force, mass, free, x, v, dt):
    """Semi-implicit (symplectic) Euler, first order, as in the seed.

    v' = v + dt F(x, v) / m, then x' = x + dt v'.
    """
    v = jnp.where(free, v + dt * force(x, v) / mass, 0.0)
    return x + dt * v, v


def verlet(force, mass, free, x, v, dt):
    """Velocity Verlet (kick-drift-kick), second order, symplectic for conservative forces.

    The closing half kick needs the acceleration at the new position and velocity;
    the velocity there is predicted as v + dt a(x, v), which is accurate to O(dt^2), so
    the step stays second order with velocity-dependent forces (damping, drag) at two
    force evaluations per step. Without them it is exactly velocity Verlet.
    """
    accel = _acceleration(force, mass, free)
    a0 = accel(x, v)
    v_half = jnp.where(free, v + 0.5 * dt * a0, 0.0)
    x_new = x + dt * v_half
    v_predicted = jnp.where(free, v + dt * a0, 0.0)
    v_new = jnp.where(free, v_half + 0.5 * dt * accel(x_new, v_predicted), 0.0)
    return x_new, v_new


def rk4(force, mass, free, x, v, dt):
    """Classic fourth-order Runge-Kutta on (x, v), four force evaluations per step."""
    accel = _acceleration(force, mass, free)
    v = jnp.where(free, v, 0.0)

    def rate(xi, vi):
        return vi, accel(xi, vi)

    k1x, k1v = rate(x, v)
    k2x, k2v = rate(x + 0.5 * dt * k1x, v + 0.5 * dt * k1v)
    k3x, k3v = rate(x + 0.5 * dt * k2x, v + 0.5 * dt * k2v)
    k4x, k4v = rate(x + dt * k3x, v + dt * k3v)
    x_new = x + dt / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x)
    v_new = v + dt / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return x_new, jnp.where(free, v_new, 0.0)


@dataclasses.dataclass(frozen=True)
class NewtonSettings:
    """Backward Euler's solver: Newton iterations, each a conjugate-gradient solve.

    Attributes:
        tolerance: stop when |residual| <= tolerance * (|M v| + dt |F(x, v)| + tiny);
            None picks 1e-12 in float64 and 1e-5 in float32.
        max_newton: most Newton iterations per step.
        cg_tolerance: relative tolerance of each inner CG solve (inexact Newton).
        max_cg: most CG iterations per solve.
    """

    tolerance: float | None = None
    max_newton: int = 20
    cg_tolerance: float = 1e-8
    max_cg: int = 200


NEWTON = NewtonSettings()


def backward_euler(force, mass, free, x, v, dt, settings: NewtonSettings = NEWTON):
    """Implicit (backward) Euler, first order, unconditionally stable.

    Solves for the new velocity w:  M (w - v) = dt F(x + dt w, w),  then x' = x + dt w.
    Newton's method; each Newton step solves with conjugate gradients on the symmetric
    part of the Jacobian M - dt dF/dv - dt^2 dF/dx (exactly symmetric without spring
    damping; the damping's geometric term adds a small skew part, which only slows
    Newton from quadratic to fast linear convergence). The solution is differentiated
    by the implicit function theorem (`jax.lax.custom_root`): the tangent and adjoint
    systems are solved with the exact Jacobian by GMRES, never by unrolling Newton.
    """
    shape, dtype = x.shape, x.dtype
    weight = jnp.where(free, mass, 0.0)
    keep = free.astype(dtype)

    def residual(w_flat):
        w = w_flat.reshape(shape) * keep
        r = keep * (weight * (w - v) - dt * force(x + dt * w, w))
        return (r + (1.0 - keep) * w_flat.reshape(shape)).reshape(-1)

    if settings.tolerance is None:
        tolerance = 1e-12 if dtype == jnp.float64 else 1e-5
    else:
        tolerance = settings.tolerance
    scale = jnp.linalg.norm(weight * v) + dt * jnp.linalg.norm(keep * force(x, v)) + jnp.finfo(dtype).tiny
    limit = tolerance * scale

    def newton(f, w0):
        def body(carry):
            w, _, count = carry
            r, linear = jax.linearize(f, w)
            transposed = jax.linear_transpose(linear, w)

            def symmetric(u):
                return 0.5 * (linear(u) + transposed(u)[0])

            step, _ = cg(symmetric, -r, tol=settings.cg_tolerance, maxiter=settings.max_cg)
            w = w + step
            return w, jnp.linalg.norm(f(w)), count + 1

        def going(carry):
            _, norm, count = carry
            return (norm > limit) & (count < settings.max_newton)

        w, _, _ = jax.lax.while_loop(going, body, (w0, jnp.linalg.norm(f(w0)), 0))
        return w

    def tangent_solve(linear, b):
        def solve(matvec, rhs):
            return gmres(matvec, rhs, tol=1e-12 if dtype == jnp.float64 else 1e-6, restart=30, maxiter=20)[0]

        return jax.lax.custom_linear_solve(linear, b, solve=solve, transpose_solve=solve)

    guess = jnp.where(free, v + dt * force(x, v) / mass, 0.0).reshape(-1)
    w = jax.lax.custom_root(residual, guess, newton, tangent_solve).reshape(shape)
    w = jnp.where(free, w, 0.0)
    return x + dt * w, w


@dataclasses.dataclass(frozen=True)
class Integrator:
    """An integrator and what is known about it."""

    name: str
    step: callable
    order: int
    explicit: bool
    description: str


INTEGRATORS = {
    i.name: i
    for i in (
        Integrator("semi_implicit_euler", semi_implicit_euler, 1, True, "the seed's; symplectic, 1 force/step"),
        Integrator("verlet", verlet, 2, True, "velocity Verlet; symplectic, 2 forces/step"),
        Integrator("rk4", rk4, 4, True, "classic Runge-Kutta; 4 forces/step, slowly loses energy"),
        Integrator("backward_euler", backward_euler, 1, False, "implicit; unconditionally stable, damps"),
    )
}


def step(model, params, state: State) -> State:
    """Advance `state`, in the model's internal layout, by one step `model.dt`.

    Lattice models work in grid layout (3, *shape) with the grid force; others in
    (N, 3). The integrators only combine arrays elementwise around the force, so the
    same code serves both. (`model.step` takes and returns the (N, 3) layout.)
    """
    integrator = INTEGRATORS[model.integrator].step
    if not INTEGRATORS[model.integrator].explicit:  # Newton needs forward mode
        model = model.forward_mode()
    if model.grid:
        force = lambda x, v: model.grid_force(params, x, v)  # noqa: E731
        mass, free = model.to_grid(model.mass), model.to_grid(~model.pinned)
    else:
        force = lambda x, v: model.force(params, x, v)  # noqa: E731
        mass, free = model.mass[:, None], (~model.pinned)[:, None]
    x, v = integrator(force, mass, free, state.x, state.v, model.dt)
    return State(x=x, v=v)
