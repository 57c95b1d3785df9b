"""The native springs stepper: the generic layout, its spring and bending forces by the C++ kernels.

Any topology and any explicit integrator; the other force terms run in JAX. Reverse
mode and vmap through the kernel's custom VJP; forward mode (and so backward Euler's
Newton solve) runs on its pure-JAX twin, the generic stepper, with the same layout.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax.numpy as jnp

from .base import Generic, Stepper
from .native_kernels import bending_force, spring_force

SPRINGS, BENDING = "springs", "bending"


@dataclasses.dataclass(frozen=True)
class NativeSprings(Stepper):
    """Generic layout; the springs and bending terms' forces from `native_kernels`."""

    name: ClassVar[str] = "native_springs"
    forward_mode: ClassVar[bool] = False

    def pure_jax(self) -> Stepper:
        return Generic()

    def internal_force(self, model, params, x, v):
        total = jnp.zeros_like(x)
        for term in model.force_terms:
            if term.name == SPRINGS:
                total = total + spring_force(
                    x, v, model.springs, model.rest_length, model.per_spring(params.ks), model.per_spring(params.kd)
                )
            elif term.name == BENDING:
                total = total + bending_force(
                    x, v, model.bends, model.bend_length, model.rest_curvature, params.kb, params.kbd
                )
            else:
                total = total + term.force(model, params, x, v)
        return total
