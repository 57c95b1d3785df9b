"""A scene: a model, its params and an initial state, ready to simulate."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import InputError
from ..steppers import check_backend
from .checks import check_params, check_representable
from .integrators import as_integrator
from .model import Model
from .params import Params, split_name
from .state import State


@dataclasses.dataclass(frozen=True)
class Scene:
    """A world ready to simulate.

    Attributes:
        name: scene name.
        model: static structure (`Model`).
        params: physical parameters (`Params`).
        state: initial state (`State`), x and v of shape (N, 3).
        faces: triangles for rendering, int (F, 3), possibly empty.
        steps: default number of steps for `jaxspring run`.
        save_every: default frame stride.
        lattice_shape: particles along each lattice axis when the scene is a lattice, else None.
        description: free text from the scene file.

    Example:
        >>> scene = js.load_scene("chain")
        >>> scene = scene.with_params(ks=600.0)
    """

    name: str
    model: Model
    params: Params
    state: State
    faces: np.ndarray
    steps: int = 1000
    save_every: int = 10
    lattice_shape: tuple | None = None
    description: str = ""

    def with_params(self, **values) -> Scene:
        """A copy with some parameters replaced (validated); a spring group's value by its
        dotted name goes through `with_values`.

        Example:
            >>> scene.with_params(ks=600.0, kd={"stretch": 2.0, "bend": 0.1})
        """
        return self.with_values(values)

    def with_values(self, values: dict) -> Scene:
        """A copy with parameters replaced by name, "ks" or "ks.<group>" (validated).

        Example:
            >>> scene.with_values({"ks.bend": 12.0, "cd": 0.02})
        """
        unknown = [k for k in values if split_name(k)[0] not in Params.names()]
        if unknown:
            raise InputError(unknown[0], "is not a parameter", f"use one of {', '.join(Params.names())}")
        for name, value in values.items():
            check_representable(name, value, self.model.mass.dtype)
        return dataclasses.replace(self, params=check_params(self.model, self.model.params_with(self.params, values)))

    def with_integrator(self, integrator) -> Scene:
        """A copy that steps with another integrator: an `Integrator` or a name in `INTEGRATORS`.

        Example:
            >>> scene.with_integrator(js.sim.BackwardEuler(newton=js.sim.NewtonSettings(max_newton=40)))
        """
        return dataclasses.replace(self, model=self.model.replace(integrator=as_integrator(integrator)))

    def with_backend(self, name: str) -> Scene:
        """A copy on backend `name`: "auto", "jax" or "native" (see `jaxspring.steppers.select_stepper`)."""
        return dataclasses.replace(self, model=self.model.replace(backend=check_backend(name)))

    def with_dt(self, dt: float) -> Scene:
        """A copy that steps with another dt [s]."""
        try:
            if isinstance(dt, (str, bytes, bool)):
                raise TypeError
            dt = float(dt)
        except (TypeError, ValueError):
            raise InputError("dt", f"must be a number, got {dt!r}", "give a time step in seconds, e.g. 0.001") from None
        if not (math.isfinite(dt) and dt > 0):
            raise InputError("dt", f"must be a finite number > 0, got {dt}", "give a positive time step")
        return dataclasses.replace(self, model=self.model.replace(dt=dt))

    def with_state(self, state: State) -> Scene:
        """A copy that starts from another state (same particle count)."""
        if state.x.shape != self.state.x.shape or state.v.shape != self.state.v.shape:
            raise InputError(
                "state", f"shape {state.x.shape} differs from the scene's {self.state.x.shape}", "give x, v of (N, 3)"
            )
        return dataclasses.replace(self, state=state)
