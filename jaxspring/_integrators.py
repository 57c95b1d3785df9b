"""Time integrators: `integrator(model, params, state) -> next state`."""

from __future__ import annotations

import jax.numpy as jnp

from ._state import State


def semi_implicit_euler(model, params, state: State) -> State:
    """One step of semi-implicit (symplectic) Euler, first order.

    v' = v + dt F(x, v) / m, then x' = x + dt v'. Pinned particles keep x and
    have v = 0.

    Example:
        >>> next_state = semi_implicit_euler(scene.model, scene.params, scene.state)
    """
    force = model.force(params, state.x, state.v)
    free = (~model.pinned)[:, None]
    v = jnp.where(free, state.v + model.dt * force / model.mass[:, None], 0.0)
    x = state.x + model.dt * v
    return State(x=x, v=v)


INTEGRATORS = {
    "semi_implicit_euler": semi_implicit_euler,
}
