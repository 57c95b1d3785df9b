"""The stepper interface, and the generic stepper (any topology, pure JAX).

A stepper is how a model's steps run: the layout its states live in while a rollout
runs, one step, and `steps` steps. A model holds one (chosen once, when it is built,
by `select_stepper`); rollouts, fits and the stability analyser only talk to it.

The physics stays in the model: its force terms (each with a `force` in (N, 3) layout
and, where it has one, a `grid_force` in grid layout) and its integrator object (whose
`step(force, mass, free, x, v, dt)` combines arrays elementwise around the force, so it
serves every layout). A stepper says which terms and integrators it runs; a model whose
terms or integrator a stepper does not run is refused when it is built.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class Stepper:
    """Base class: the generic layout (N, 3), a `lax.scan` of integrator steps.

    Class attributes:
        name: the stepper's name (shown in benchmarks and errors).
        layout: "particles" ((N, 3) arrays) or "grid" ((3, *lattice shape), see `layout`).
        forward_mode: whether jvp/jacfwd run through it (the native kernels are reverse-mode only).
        fused: whether `advance` runs many steps in one call that keeps its own
            reverse-mode checkpoints (rollouts then do not checkpoint inside it).
        terms: names of the force terms it runs; None: every term with a `force`.
        integrators: names of the integrators it runs; None: all.
    """

    name: ClassVar[str] = "generic"
    layout: ClassVar[str] = "particles"
    forward_mode: ClassVar[bool] = True
    fused: ClassVar[bool] = False
    terms: ClassVar[frozenset | None] = None
    integrators: ClassVar[frozenset | None] = None

    def refusal(self, model) -> str | None:
        """Why this stepper cannot run `model` (None when it can)."""
        if self.integrators is not None and model.integrator.name not in self.integrators:
            return f"the {self.name} stepper runs {', '.join(sorted(self.integrators))}, not {model.integrator.name}"
        for term in model.force_terms:
            if not self.runs_term(term):
                return f"the {self.name} stepper does not run the force term {term.name!r}"
        return None

    def runs_term(self, term) -> bool:
        return self.terms is None or term.name in self.terms

    def pure_jax(self) -> Stepper:
        """The pure-JAX stepper with the same layout (for forward mode)."""
        return self

    # layout ------------------------------------------------------------------------------

    def array_to_internal(self, model, values: jax.Array) -> jax.Array:
        """(N, 3) -> this stepper's layout."""
        return values

    def array_from_internal(self, model, values: jax.Array) -> jax.Array:
        """This stepper's layout, with any leading axes (..., layout) -> (..., N, 3)."""
        return values

    def to_internal(self, model, state):
        """The state in the layout this stepper works in."""
        return state.replace(x=self.array_to_internal(model, state.x), v=self.array_to_internal(model, state.v))

    def from_internal(self, model, state):
        return state.replace(x=self.array_from_internal(model, state.x), v=self.array_from_internal(model, state.v))

    # physics -----------------------------------------------------------------------------

    def internal_force(self, model, params, x, v):
        """Total force [N] in this stepper's layout."""
        total = jnp.zeros_like(x)
        for term in model.force_terms:
            total = total + term.force(model, params, x, v)
        return total

    def force(self, model, params, x, v):
        """Total force [N] on every particle, (N, 3) in and out."""
        inside = lambda values: self.array_to_internal(model, values)  # noqa: E731
        return self.array_from_internal(model, self.internal_force(model, params, inside(x), inside(v)))

    def mass_and_free(self, model):
        """Masses and the not-pinned mask, shaped to broadcast against an internal state."""
        return model.mass[:, None], (~model.pinned)[:, None]

    def step(self, model, params, state, driven=None):
        """One step of `model.dt` on a state in the internal layout.

        Pinned particles hold still and leave the step at rest. `driven`, a mask
        broadcasting against the state, marks particles moved from outside: they keep the
        velocity they enter with over the step (see `sim.driven`).
        """
        stepper = self if model.integrator.explicit else self.pure_jax()  # Newton needs forward mode
        mass, movable = stepper.mass_and_free(model)
        free = movable if driven is None else movable & ~driven
        x, v = model.integrator.step(
            lambda x, v: stepper.internal_force(model, params, x, v), mass, free, state.x, state.v, model.dt
        )
        # pinned particles stay where they are and leave the step at rest (as the native kernels do)
        return state.replace(x=jnp.where(movable, x, state.x), v=jnp.where(movable, v, 0.0))

    def advance(self, model, params, state, steps: int):
        """`steps` steps (static) on a state in the internal layout."""
        return jax.lax.scan(lambda current, _: (self.step(model, params, current), None), state, None, length=steps)[0]


@dataclasses.dataclass(frozen=True)
class Generic(Stepper):
    """Any topology in pure JAX: spring forces by gather and scatter-add (`segment_sum`)."""

    name: ClassVar[str] = "generic"
