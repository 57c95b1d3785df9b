"""The native lattice stepper: whole semi-implicit Euler steps of a lattice in C++.

`advance` is one call of `native_kernels.lattice_advance` for any number of steps
(springs, drag, gravity and ground fused into one pass per step), with a native
reverse pass that keeps its own checkpoints. Grid layout, like its pure-JAX twin,
the grid stepper, which forward mode and single force evaluations use.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from .grid import Grid
from .native_kernels import lattice_advance


@dataclasses.dataclass(frozen=True)
class NativeLattice(Grid):
    """Lattice models with semi-implicit Euler and the four built-in force terms, in one native call."""

    name: ClassVar[str] = "native_lattice"
    forward_mode: ClassVar[bool] = False
    fused: ClassVar[bool] = True
    terms: ClassVar[frozenset] = frozenset({"springs", "drag", "gravity", "ground"})
    integrators: ClassVar[frozenset] = frozenset({"semi_implicit_euler"})

    def pure_jax(self) -> Grid:
        return Grid()

    def step(self, model, params, state):
        return self.advance(model, params, state, 1)

    def advance(self, model, params, state, steps: int):
        x, v = lattice_advance(model, params, state.x, state.v, steps)
        return state.replace(x=x, v=v)
