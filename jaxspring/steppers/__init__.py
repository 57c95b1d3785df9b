"""Steppers: one per backend behind one interface (`Stepper`), chosen once per model.

| stepper          | layout        | runs                                   | forward mode |
|------------------|---------------|----------------------------------------|--------------|
| `Generic`        | (N, 3)        | any topology, any term, any integrator | yes          |
| `Grid`           | (3, *shape)   | lattices; terms with a `grid_force`    | yes          |
| `NativeSprings`  | (N, 3)        | any topology; springs, bending in C++  | no (Generic) |
| `NativeLattice`  | (3, *shape)   | lattices, semi-implicit Euler, the four built-in terms, whole steps in C++ | no (Grid) |

`select_stepper` maps a model's backend ("auto", "jax" or "native") to one of them.
"""

from __future__ import annotations

import jax

from ..errors import InputError
from . import native_kernels
from .base import Generic, Stepper
from .grid import Grid

BACKENDS = ("auto", "jax", "native")


def check_backend(name: str) -> str:
    """Validate a backend name; "native" without the built kernel becomes "jax" with a notice (once).

    Example:
        >>> check_backend("auto")
        'auto'
    """
    if name not in BACKENDS:
        raise InputError("backend", f"unknown backend {name!r}", f"use one of {', '.join(BACKENDS)}")
    if name == "native" and not native_kernels.available():
        native_kernels.notice_unavailable()
        return "jax"
    return name


def select_stepper(model) -> Stepper:
    """The stepper for `model`, from its backend:

    - "jax": `Grid` for a lattice whose terms all have a grid force, else `Generic`;
    - "native": `NativeLattice` where it runs the model, else `NativeSprings`;
    - "auto" (the default): on CPU where the kernels are built, `NativeLattice` where it runs
      the model (lattices with semi-implicit Euler: several times faster), else
      `NativeSprings` for models with the bending term (its gradient through a cable's
      rollout 2.5x faster than in JAX), else as "jax".

    Example:
        >>> select_stepper(js.load_scene("cloth").model).name
        'native_lattice'
    """
    backend = check_backend(model.backend)
    candidates = []
    if backend == "native" or (backend == "auto" and _native_is_faster()):
        from .native_lattice import NativeLattice

        candidates.append(NativeLattice())
    if backend == "native" or (backend == "auto" and _native_is_faster() and _bends(model)):
        from .native_springs import NativeSprings

        candidates.append(NativeSprings())
    candidates += [Grid(), Generic()]
    for stepper in candidates:
        if stepper.refusal(model) is None:
            return stepper
    raise InputError("model", Generic().refusal(model), "give every force term a `force` method")


def _bends(model) -> bool:
    return any(term.name == "bending" for term in model.force_terms)


def _native_is_faster() -> bool:
    # not cached here: `available` is, and clearing its cache (a test that hides the kernel)
    # must not leave every later model of the process on pure JAX
    return native_kernels.available() and jax.default_backend() == "cpu"


__all__ = ["BACKENDS", "Generic", "Grid", "Stepper", "check_backend", "select_stepper"]
