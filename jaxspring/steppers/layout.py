"""Grid layout of a lattice: arrays (3, *shape), components first.

In grid layout a lattice's spring families are shifts along its axes and the innermost
loop runs along the lattice's last axis (vectorisable), not over 3 components.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def to_grid(shape: tuple, values) -> jax.Array:
    """(N, 3) -> (3, *shape); (N,) -> (1, *shape); a scalar stays a scalar.

    Example:
        >>> to_grid((2, 3), jnp.zeros((6, 3))).shape   # (3, 2, 3)
    """
    values = jnp.asarray(values)
    if values.ndim == 0:
        return values
    if values.ndim == 1:
        return values.reshape((1,) + tuple(shape))
    return jnp.moveaxis(values, -1, 0).reshape((3,) + tuple(shape))


def from_grid(values: jax.Array) -> jax.Array:
    """(3, *shape) -> (N, 3).

    Example:
        >>> from_grid(jnp.zeros((3, 2, 3))).shape   # (6, 3)
    """
    return jnp.moveaxis(values.reshape((3, -1)), 0, -1)
