"""Differentiable physical parameters of a scene."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..errors import InputError

# name -> (unit, what it is, which axis a per-item array runs over)
PARAMETER_INFO = {
    "ks": ("N/m", "spring stiffness", "spring"),
    "kd": ("N s/m", "spring damping along the spring", "spring"),
    "cd": ("N s^2/m^2", "quadratic air-drag coefficient", "particle"),
    "kg": ("N/m", "ground penalty stiffness", "particle"),
    "kgd": ("N s/m", "ground penalty damping", "particle"),
    "ground_height": ("m", "height h of the ground plane y = h", None),
    "gravity": ("m/s^2", "gravitational acceleration vector", None),
    "kb": ("N m^2", "bending stiffness (EI) of the bend triples", "bend"),
    "kbd": ("N m^2 s", "bending damping of the bend triples", "bend"),
}
# Parameters that must be strictly positive for a log-space fit and >= 0 physically.
NON_NEGATIVE = ("ks", "kd", "cd", "kg", "kgd", "kb", "kbd")
# Parameters that may be given per spring group, {group name: value}.
PER_GROUP = ("ks", "kd")


def split_name(name: str) -> tuple[str, str | None]:
    """ "ks.stretch" -> ("ks", "stretch"); "ks" -> ("ks", None).

    Example:
        >>> split_name("kd.bend")
        ('kd', 'bend')
    """
    base, dot, group = name.partition(".")
    return base, (group if dot else None)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Params:
    """Physical parameters; `None` means the scene has no such force.

    Each of ks, kd is a scalar, one value per spring, shape (S,), or one entry per
    spring group, {group name: scalar or (springs of the group,)} (see
    `Model.spring_groups`); cd, kg, kgd a scalar or one value per particle, shape (N,).
    A group's value is named "ks.<group>" wherever parameters are named (fits, files,
    `--set`).

    Attributes:
        ks: spring stiffness [N/m].
        kd: spring damping along the spring [N s/m].
        cd: quadratic air drag, f = -cd |v| v [N s^2/m^2].
        kg: ground penalty stiffness [N/m].
        kgd: ground penalty damping [N s/m].
        ground_height: height h of the ground plane y = h [m].
        gravity: gravitational acceleration [m/s^2], shape (3,).
        kb: bending stiffness EI of the bend triples [N m^2], a scalar or shape (B,).
        kbd: bending damping of the bend triples [N m^2 s], a scalar or shape (B,).

    Example:
        >>> p = Params(ks=1000.0, kd=5.0, cd=0.05, gravity=[0.0, -9.81, 0.0])
        >>> p = p.replace(ks=600.0)
        >>> p = p.replace(ks={"stretch": 1000.0, "bend": 10.0}).with_values({"ks.bend": 12.0})
    """

    ks: jax.Array | None = None
    kd: jax.Array | None = None
    cd: jax.Array | None = None
    kg: jax.Array | None = None
    kgd: jax.Array | None = None
    ground_height: jax.Array | None = None
    gravity: jax.Array | None = None
    kb: jax.Array | None = None
    kbd: jax.Array | None = None

    def __post_init__(self):
        # Accept Python floats and lists; leave tracers, arrays and ints alone (so a
        # Params of ints/None can serve as `in_axes` for jax.vmap).
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, (float, list, tuple)):
                object.__setattr__(self, field.name, jnp.asarray(value, dtype=float))
            elif isinstance(value, dict):
                cast = {
                    k: jnp.asarray(v, dtype=float) if isinstance(v, (float, list, tuple)) else v
                    for k, v in value.items()
                }
                object.__setattr__(self, field.name, cast)

    def replace(self, **changes) -> Params:
        """Return a copy with some parameters replaced."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The parameters that are present, as a name -> array dict; a per-group parameter
        gives one entry per group, "ks.<group>"."""
        flat = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, dict):
                flat.update({f"{field.name}.{group}": v for group, v in value.items()})
            elif value is not None:
                flat[field.name] = value
        return flat

    def get(self, name: str):
        """The value of a parameter by name, "ks" or "ks.<group>" (a scalar ks serves every group)."""
        base, group = split_name(name)
        value = getattr(self, base)
        if group is None or not isinstance(value, dict):
            return value
        return value[group]

    def with_values(self, values: dict) -> Params:
        """A copy with parameters replaced by name, "ks" or "ks.<group>" (the other groups keep
        their values; a scalar or per-spring ks becomes per group only through `Model.per_group`).

        Example:
            >>> params.with_values({"ks.stretch": 900.0, "cd": 0.02})
        """
        changes = {}
        for name, value in values.items():
            base, group = split_name(name)
            if group is None:
                changes[base] = value
                continue
            current = changes.get(base, getattr(self, base))
            if not isinstance(current, dict):
                raise InputError(
                    name, f"{base} is not given per spring group", f"give {base} as {{group = value}} first"
                )
            changes[base] = {**current, group: value}
        return self.replace(**changes)

    @classmethod
    def from_values(cls, values: dict) -> Params:
        """Params from name -> value with "ks.<group>" names gathered into group dicts (files)."""
        return cls().with_values(
            {**{base: {} for base in {split_name(n)[0] for n in values if split_name(n)[1]}}, **values}
        )

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))
