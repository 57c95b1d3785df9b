"""Time integrators.

Each integrator is a pure function `(force, mass, free, x, v, dt) -> (x', v')`:
`force(x, v)` is the total force (N, 3), `mass` the masses as a column (N, 1),
`free` a boolean column (N, 1) that is False for particles moved from outside:
they keep the velocity they enter the step with, so a pinned particle (v = 0) stays
put and a driven one moves along its path over the step (see `sim.driven`). Written against a force function rather than a model, the same
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

from ..errors import InputError


def _acceleration(force, mass, free):
    return lambda x, v: jnp.where(free, force(x, v) / mass, 0.0)


def semi_implicit_euler(force, mass, free, x, v, dt):
    """Semi-implicit (symplectic) Euler, first order, as in the seed.

    v' = v + dt F(x, v) / m, then x' = x + dt v'.
    """
    v = v + dt * _acceleration(force, mass, free)(x, v)
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
    v_half = v + 0.5 * dt * a0
    x_new = x + dt * v_half
    v_new = v_half + 0.5 * dt * accel(x_new, v + dt * a0)
    return x_new, v_new


def rk4(force, mass, free, x, v, dt):
    """Classic fourth-order Runge-Kutta on (x, v), four force evaluations per step."""
    accel = _acceleration(force, mass, free)

    def rate(xi, vi):
        return vi, accel(xi, vi)

    k1x, k1v = rate(x, v)
    k2x, k2v = rate(x + 0.5 * dt * k1x, v + 0.5 * dt * k1v)
    k3x, k3v = rate(x + 0.5 * dt * k2x, v + 0.5 * dt * k2v)
    k4x, k4v = rate(x + dt * k3x, v + dt * k3v)
    x_new = x + dt / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x)
    v_new = v + dt / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return x_new, v_new


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

    def residual(w_flat):  # a particle that is not free keeps its velocity: w = v
        w = jnp.where(free, w_flat.reshape(shape), v)
        r = keep * (weight * (w - v) - dt * force(x + dt * w, w))
        return (r + (1.0 - keep) * (w_flat.reshape(shape) - v)).reshape(-1)

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

    guess = jnp.where(free, v + dt * force(x, v) / mass, v).reshape(-1)
    w = jax.lax.custom_root(residual, guess, newton, tangent_solve).reshape(shape)
    w = jnp.where(free, w, v)
    return x + dt * w, w


class Integrator:
    """A time integrator: a configured, hashable object whose `step` advances (x, v) by dt.

    Subclasses set `name`, `order`, `explicit` and `description`, and either `function`
    (a step function of this module) or their own `step(force, mass, free, x, v, dt) ->
    (x', v')` (see the module docstring). A model holds one as its static `integrator`;
    scene files name one (`INTEGRATORS` maps each name to its default instance).
    """

    name: str = ""
    order: int = 0
    explicit: bool = True
    description: str = ""
    function = None

    def step(self, force, mass, free, x, v, dt):
        return type(self).function(force, mass, free, x, v, dt)

    def __str__(self) -> str:
        return self.name


@dataclasses.dataclass(frozen=True)
class SemiImplicitEuler(Integrator):
    """The seed's integrator: v' = v + dt F(x, v) / m, then x' = x + dt v'.

    Example:
        >>> scene = js.load_scene("chain").with_integrator(js.sim.SemiImplicitEuler())
    """

    name = "semi_implicit_euler"
    order = 1
    description = "the seed's; symplectic, 1 force/step"
    function = staticmethod(semi_implicit_euler)


@dataclasses.dataclass(frozen=True)
class Verlet(Integrator):
    """Velocity Verlet, second order (see `verlet`).

    Example:
        >>> scene = js.load_scene("chain").with_integrator(js.sim.Verlet())
    """

    name = "verlet"
    order = 2
    description = "velocity Verlet; symplectic, 2 forces/step"
    function = staticmethod(verlet)


@dataclasses.dataclass(frozen=True)
class RK4(Integrator):
    """Classic fourth-order Runge-Kutta (see `rk4`).

    Example:
        >>> scene = js.load_scene("chain").with_integrator(js.sim.RK4())
    """

    name = "rk4"
    order = 4
    description = "classic Runge-Kutta; 4 forces/step, slowly loses energy"
    function = staticmethod(rk4)


@dataclasses.dataclass(frozen=True)
class BackwardEuler(Integrator):
    """Implicit Euler with a configurable Newton-CG solve (see `backward_euler`).

    Attributes:
        newton: the solver's settings (`NewtonSettings`).

    Example:
        >>> stiff = js.sim.BackwardEuler(newton=js.sim.NewtonSettings(tolerance=1e-10, max_newton=30))
        >>> scene = js.load_scene("hard/stiff_cloth").with_integrator(stiff)
    """

    newton: NewtonSettings = NEWTON
    name = "backward_euler"
    order = 1
    explicit = False
    description = "implicit; unconditionally stable, damps"

    def step(self, force, mass, free, x, v, dt):
        return backward_euler(force, mass, free, x, v, dt, self.newton)


INTEGRATORS = {i.name: i for i in (SemiImplicitEuler(), Verlet(), RK4(), BackwardEuler())}


def as_integrator(value) -> Integrator:
    """An `Integrator` from itself or from its name in `INTEGRATORS`.

    Example:
        >>> as_integrator("rk4")   # RK4()
    """
    if isinstance(value, Integrator):
        return value
    if isinstance(value, str) and value in INTEGRATORS:
        return INTEGRATORS[value]
    raise InputError("integrator", f"unknown integrator {value!r}", f"use one of {', '.join(INTEGRATORS)}")
