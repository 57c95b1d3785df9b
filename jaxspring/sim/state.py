"""Simulation state and trajectories as frozen pytrees."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """Positions and velocities of all particles.

    Attributes:
        x: positions [m], shape (N, 3).
        v: velocities [m/s], shape (N, 3).

    Example:
        >>> state = State(x=jnp.zeros((2, 3)), v=jnp.zeros((2, 3)))
    """

    x: jax.Array
    v: jax.Array

    def replace(self, **changes) -> State:
        """Return a copy with some fields replaced."""
        return dataclasses.replace(self, **changes)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Trajectory:
    """Saved frames of a rollout; frame 0 is the initial state.

    Attributes:
        x: positions [m], shape (frames, N, 3).
        v: velocities [m/s], shape (frames, N, 3).
        t: time of each frame [s], shape (frames,).
    """

    x: jax.Array
    v: jax.Array
    t: jax.Array

    @property
    def frame_count(self) -> int:
        return int(self.x.shape[-3])

    def stride(self, dt: float) -> int:
        """Time steps between saved frames, for a rollout with time step `dt` [s]."""
        t = np.asarray(self.t)
        return max(1, int(round(float(t[1] - t[0]) / dt))) if t.shape[0] > 1 else 1

    def frame(self, index: int) -> State:
        """The state at one saved frame (negative indices count from the end)."""
        return State(x=self.x[..., index, :, :], v=self.v[..., index, :, :])


def as_state(x, v=None) -> State:
    """Build a State from array-likes; `v` defaults to rest.

    Example:
        >>> s = as_state([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    """
    x = jnp.asarray(x, dtype=float)
    v = jnp.zeros_like(x) if v is None else jnp.asarray(v, dtype=float)
    return State(x=x, v=v)
