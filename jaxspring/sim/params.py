"""Differentiable physical parameters of a scene."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

# name -> (unit, what it is, which axis a per-item array runs over)
PARAMETER_INFO = {
    "ks": ("N/m", "spring stiffness", "spring"),
    "kd": ("N s/m", "spring damping along the spring", "spring"),
    "cd": ("N s^2/m^2", "quadratic air-drag coefficient", "particle"),
    "kg": ("N/m", "ground penalty stiffness", "particle"),
    "kgd": ("N s/m", "ground penalty damping", "particle"),
    "ground_height": ("m", "height h of the ground plane y = h", None),
    "gravity": ("m/s^2", "gravitational acceleration vector", None),
}
# Parameters that must be strictly positive for a log-space fit and >= 0 physically.
NON_NEGATIVE = ("ks", "kd", "cd", "kg", "kgd")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Params:
    """Physical parameters; `None` means the scene has no such force.

    Each of ks, kd is a scalar or one value per spring, shape (S,); cd, kg, kgd
    a scalar or one value per particle, shape (N,).

    Attributes:
        ks: spring stiffness [N/m].
        kd: spring damping along the spring [N s/m].
        cd: quadratic air drag, f = -cd |v| v [N s^2/m^2].
        kg: ground penalty stiffness [N/m].
        kgd: ground penalty damping [N s/m].
        ground_height: height h of the ground plane y = h [m].
        gravity: gravitational acceleration [m/s^2], shape (3,).

    Example:
        >>> p = Params(ks=1000.0, kd=5.0, cd=0.05, gravity=[0.0, -9.81, 0.0])
        >>> p = p.replace(ks=600.0)
    """

    ks: jax.Array | None = None
    kd: jax.Array | None = None
    cd: jax.Array | None = None
    kg: jax.Array | None = None
    kgd: jax.Array | None = None
    ground_height: jax.Array | None = None
    gravity: jax.Array | None = None

    def __post_init__(self):
        # Accept Python floats and lists; leave tracers, arrays and ints alone (so a
        # Params of ints/None can serve as `in_axes` for jax.vmap).
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, (float, list, tuple)):
                object.__setattr__(self, field.name, jnp.asarray(value, dtype=float))

    def replace(self, **changes) -> Params:
        """Return a copy with some parameters replaced."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The parameters that are present, as a name -> array dict."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))
