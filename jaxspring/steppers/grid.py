"""The grid stepper: a lattice in pure JAX, its spring families as array shifts.

States live in grid layout (3, *shape) (see `layout`); each force term runs its
`grid_force`, which for the springs is one difference of two shifted views per
neighbour family (no gather, no scatter). Same numbers as the generic stepper.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from .base import Stepper
from .layout import to_grid


@dataclasses.dataclass(frozen=True)
class Grid(Stepper):
    """Lattice models (springs that are whole neighbour families) in grid layout, pure JAX."""

    name: ClassVar[str] = "grid"
    layout: ClassVar[str] = "grid"

    def refusal(self, model) -> str | None:
        if model.lattice is None:
            return f"the {self.name} stepper needs a lattice (springs that are whole neighbour families)"
        return super().refusal(model)

    def runs_term(self, term) -> bool:
        return hasattr(term, "grid_force") and super().runs_term(term)

    def array_to_internal(self, model, values: jax.Array) -> jax.Array:
        return to_grid(model.lattice[0], values)

    def array_from_internal(self, model, values: jax.Array) -> jax.Array:
        lead = values.shape[: values.ndim - 1 - len(model.lattice[0])]
        return jnp.moveaxis(values.reshape(lead + (3, -1)), -2, -1)

    def internal_force(self, model, params, x, v):
        total = jnp.zeros_like(x)
        for term in model.force_terms:
            total = total + term.grid_force(model, params, x, v)
        return total

    def mass_and_free(self, model):
        shape = model.lattice[0]
        return to_grid(shape, model.mass), to_grid(shape, ~model.pinned)
