"""The static structure of a scene: topology, force terms, integrator, dt."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..sim.forces import TERM_PARAMETERS, TERMS
from ..sim.integrators import INTEGRATORS
from ..sim.integrators import step as _integrate
from ..sim.params import NON_NEGATIVE, PARAMETER_INFO, Params
from ..sim.state import State


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Model:
    """Topology (arrays) plus which force terms, integrator and dt (static).

    Attributes:
        springs: particle index pairs (a, b), int32, shape (S, 2).
        rest_length: spring rest lengths L0 [m], shape (S,).
        mass: particle masses [kg], shape (N,).
        pinned: particles that never move, bool, shape (N,).
        drag: particles that feel air resistance, bool, shape (N,).
        terms: names of the force terms, e.g. ("springs", "gravity") (static).
        integrator: name of the time integrator (static).
        dt: time step [s] (static).
        lattice: (shape, offsets) when the springs are whole lattice neighbour families
            in `lattice_springs` order (static); the spring force then runs as array
            shifts instead of scatters (same numbers, see `Springs`). None otherwise.
        backend: "jax" (default) or "native": the spring force by the C++ kernel
            (`jaxspring/steppers/native_kernels.py`; reverse mode and vmap, not forward mode), static.

    Build one with `make_model`; a loaded scene carries one as `scene.model`.
    """

    springs: jax.Array
    rest_length: jax.Array
    mass: jax.Array
    pinned: jax.Array
    drag: jax.Array
    terms: tuple = dataclasses.field(metadata=dict(static=True), default=())
    integrator: str = dataclasses.field(metadata=dict(static=True), default="semi_implicit_euler")
    dt: float = dataclasses.field(metadata=dict(static=True), default=1e-3)
    lattice: tuple | None = dataclasses.field(metadata=dict(static=True), default=None)
    backend: str = dataclasses.field(metadata=dict(static=True), default="jax")

    @property
    def particle_count(self) -> int:
        return int(self.mass.shape[0])

    @property
    def spring_count(self) -> int:
        return int(self.springs.shape[0])

    def has(self, term: str) -> bool:
        return term in self.terms

    @property
    def native_lattice(self) -> bool:
        """Whether whole steps run in the native lattice kernel (lattice, semi-implicit Euler, "native")."""
        return self.backend == "native" and self.lattice is not None and self.integrator == "semi_implicit_euler"

    @property
    def grid(self) -> bool:
        """Whether steps run in grid layout (a lattice on the pure-JAX backend or the native lattice kernel)."""
        return self.lattice is not None and (self.backend == "jax" or self.native_lattice)

    def forward_mode(self) -> Model:
        """This model on the pure-JAX backend, for jvp/jacfwd (the native kernels are reverse-mode only).

        It keeps the native model's internal layout, so states pass between them.
        """
        if self.backend == "jax":
            return self
        return self.replace(backend="jax", lattice=self.lattice if self.grid else None)

    def force(self, params: Params, x: jax.Array, v: jax.Array) -> jax.Array:
        """Total force on every particle [N], shape (N, 3)."""
        if self.grid:
            return self.from_grid(self.grid_force(params, self.to_grid(x), self.to_grid(v)))
        total = jnp.zeros_like(x)
        for name in self.terms:
            total = total + TERMS[name].force(self, params, x, v)
        return total

    # Lattice models step in "grid layout": arrays (3, *shape), components first, so the
    # spring families are shifts along the lattice axes and the innermost loop runs
    # along the lattice's last axis (vectorisable), not over 3 components.

    def to_grid(self, values: jax.Array) -> jax.Array:
        """(N, 3) -> (3, *shape); (N,) -> (1, *shape); a scalar stays a scalar."""
        shape = self.lattice[0]
        values = jnp.asarray(values)
        if values.ndim == 0:
            return values
        if values.ndim == 1:
            return values.reshape((1,) + shape)
        return jnp.moveaxis(values, -1, 0).reshape((3,) + shape)

    def from_grid(self, values: jax.Array) -> jax.Array:
        """(3, *shape) -> (N, 3)."""
        return jnp.moveaxis(values.reshape((3, -1)), 0, -1)

    def grid_force(self, params: Params, x: jax.Array, v: jax.Array) -> jax.Array:
        """Total force in grid layout (lattice models only)."""
        total = jnp.zeros_like(x)
        for name in self.terms:
            total = total + TERMS[name].grid_force(self, params, x, v)
        return total

    def to_internal(self, state: State) -> State:
        """The state in the layout the step works in (grid layout for lattices)."""
        if not self.grid:
            return state
        return State(x=self.to_grid(state.x), v=self.to_grid(state.v))

    def from_internal(self, state: State) -> State:
        if not self.grid:
            return state
        return State(x=self.from_grid(state.x), v=self.from_grid(state.v))

    def positions_from_internal(self, x: jax.Array) -> jax.Array:
        """Internal-layout positions with leading axes (..., layout) -> (..., N, 3)."""
        if not self.grid:
            return x
        lead = x.shape[: x.ndim - 1 - len(self.lattice[0])]
        return jnp.moveaxis(x.reshape(lead + (3, -1)), -2, -1)

    def energy(self, params: Params, state: State) -> jax.Array:
        """Total mechanical energy [J]: kinetic plus every term's potential."""
        kinetic = 0.5 * jnp.sum(self.mass[:, None] * state.v**2)
        potential = sum(TERMS[name].energy(self, params, state.x) for name in self.terms)
        return kinetic + potential

    def step(self, params: Params, state: State) -> State:
        """Advance one time step dt with the model's integrator."""
        return self.from_internal(self.step_internal(params, self.to_internal(state)))

    def step_internal(self, params: Params, state: State) -> State:
        """One step on a state in the internal layout (see `to_internal`)."""
        if self.native_lattice:
            return self.advance(params, state, 1)
        return _integrate(self, params, state)

    def advance(self, params: Params, state: State, steps: int) -> State:
        """`steps` steps (static) on a state in the internal layout: one native call for
        native lattice models, a `lax.scan` of `step_internal` otherwise."""
        if self.native_lattice:
            from ..steppers.native_kernels import lattice_advance

            return State(*lattice_advance(self, params, state.x, state.v, steps))
        step = lambda current, _: (self.step_internal(params, current), None)  # noqa: E731
        return jax.lax.scan(step, state, None, length=steps)[0]

    def replace(self, **changes) -> Model:
        return dataclasses.replace(self, **changes)

    def required_parameters(self) -> tuple[str, ...]:
        return tuple(p for term in self.terms for p in TERM_PARAMETERS[term])


def make_model(
    springs,
    mass,
    *,
    rest_length=None,
    positions=None,
    pinned=None,
    drag=None,
    gravity: bool = True,
    ground: bool = False,
    integrator: str = "semi_implicit_euler",
    dt: float = 1e-3,
    lattice_shape=None,
    backend: str = "jax",
) -> Model:
    """Build and validate a Model.

    Args:
        springs: index pairs, shape (S, 2).
        mass: particle masses [kg], shape (N,) or a scalar together with `positions`.
        rest_length: [m], shape (S,); default: spring lengths at `positions`.
        positions: [m], shape (N, 3); needed when `rest_length` is omitted.
        pinned: bool (N,) mask or a list of particle indices; default none.
        drag: bool (N,) mask, True/False for all; default none. Any set flag adds the drag term.
        gravity, ground: whether the scene has these terms.
        integrator: one of `jaxspring.INTEGRATORS`.
        dt: time step [s].
        lattice_shape: the particles' lattice shape when they form one (C order); if
            the springs are whole neighbour families of it, the structured fast path is used.
        backend: "jax" or "native" (the C++ spring kernel; "jax" with a notice if not built).

    Example:
        >>> model = make_model([[0, 1]], mass=[1.0, 1.0], positions=[[0, 0, 0], [0, -1, 0]],
        ...                    pinned=[0], dt=1e-3)
    """
    springs_np = np.asarray(springs, dtype=np.int64).reshape(-1, 2)
    if positions is not None:
        positions = np.asarray(positions, dtype=float)
    mass_np = np.asarray(mass, dtype=float)
    if mass_np.ndim == 0:
        if positions is None:
            raise InputError("mass", "a scalar mass needs `positions` to know N", "pass one mass per particle")
        mass_np = np.full(positions.shape[0], float(mass_np))
    count = mass_np.shape[0]
    _check_finite("mass", mass_np)
    if np.any(mass_np <= 0):
        raise InputError("mass", f"must be > 0, got {mass_np.min():g}", "give every particle a positive mass")
    if springs_np.size and (springs_np.min() < 0 or springs_np.max() >= count):
        bad = springs_np[(springs_np < 0) | (springs_np >= count)][0]
        raise InputError("springs", f"particle index {bad} out of range 0..{count - 1}", "fix the spring's endpoints")
    if np.any(springs_np[:, 0] == springs_np[:, 1]):
        i = int(np.nonzero(springs_np[:, 0] == springs_np[:, 1])[0][0])
        raise InputError("springs", f"spring {i} joins particle {springs_np[i, 0]} to itself", "remove it")
    canonical = np.sort(springs_np, axis=1)
    _, first, counts = np.unique(canonical, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        pair = canonical[first[np.argmax(counts > 1)]]
        raise InputError(
            "springs", f"duplicate spring between particles {pair[0]} and {pair[1]}", "list each pair once"
        )
    if rest_length is None:
        if positions is None:
            raise InputError("rest_length", "missing and no positions to measure it from", "give rest lengths")
        d = positions[springs_np[:, 1]] - positions[springs_np[:, 0]]
        rest_np = np.sqrt(np.sum(d * d, axis=-1))
    else:
        rest_np = np.broadcast_to(np.asarray(rest_length, dtype=float), (springs_np.shape[0],)).copy()
    _check_finite("rest_length", rest_np)
    if np.any(rest_np < 0):
        raise InputError("rest_length", "must be >= 0", "give non-negative rest lengths")
    pinned_np = _mask("pinned", pinned, count, default=False)
    drag_np = _mask("drag", drag, count, default=False)
    if integrator not in INTEGRATORS:
        raise InputError("integrator", f"unknown integrator {integrator!r}", f"use one of {', '.join(INTEGRATORS)}")
    if not (np.isfinite(dt) and dt > 0):
        raise InputError("dt", f"must be a finite number > 0, got {dt}", "set a positive time step")
    terms = []
    if springs_np.shape[0]:
        terms.append("springs")
    if drag_np.any():
        terms.append("drag")
    if gravity:
        terms.append("gravity")
    if ground:
        terms.append("ground")
    return Model(
        springs=jnp.asarray(springs_np, dtype=jnp.int32),
        rest_length=jnp.asarray(rest_np, dtype=float),
        mass=jnp.asarray(mass_np, dtype=float),
        pinned=jnp.asarray(pinned_np),
        drag=jnp.asarray(drag_np),
        terms=tuple(terms),
        integrator=integrator,
        dt=float(dt),
        lattice=lattice_layout(springs_np, lattice_shape, count),
        backend=check_backend(backend),
    )


BACKENDS = ("jax", "native")


def check_backend(name: str) -> str:
    """Validate a backend name; "native" without the built kernel falls back to "jax" with a notice."""
    if name not in BACKENDS:
        raise InputError("backend", f"unknown backend {name!r}", f"use one of {', '.join(BACKENDS)}")
    if name == "native":
        from ..steppers import native_kernels as _native

        if not _native.available():
            _native.notice_unavailable()
            return "jax"
    return name


def lattice_layout(springs: np.ndarray, shape, count: int):
    """(shape, offsets) if `springs` is a concatenation of whole lattice neighbour families.

    Family `offset` joins every particle at lattice index i to i + offset (both inside
    the lattice), in C order of i, as `lattice_springs` writes them. Returns None when
    the springs are anything else (then the generic path is used).
    """
    if shape is None or springs.shape[0] == 0:
        return None
    shape = tuple(int(n) for n in shape)
    if int(np.prod(shape)) != count:
        return None
    index = np.arange(count).reshape(shape)
    cells = np.stack(np.unravel_index(np.arange(count), shape), axis=1)
    offsets, start = [], 0
    while start < springs.shape[0]:
        offset = tuple(int(c) for c in cells[springs[start, 1]] - cells[springs[start, 0]])
        src = tuple(slice(max(0, -o), n - max(0, o)) for o, n in zip(offset, shape))
        dst = tuple(slice(max(0, o), n - max(0, -o)) for o, n in zip(offset, shape))
        family = np.stack([index[src].reshape(-1), index[dst].reshape(-1)], axis=1)
        end = start + family.shape[0]
        if family.shape[0] == 0 or not np.array_equal(springs[start:end], family) or offset in offsets:
            return None
        offsets.append(offset)
        start = end
    return shape, tuple(offsets)


def check_params(model: Model, params: Params) -> Params:
    """Validate `params` against `model`: present where needed, absent otherwise, shapes, signs.

    Returns the params with values cast to the default float dtype.
    """
    needed = set(model.required_parameters())
    for name in Params.names():
        value = getattr(params, name)
        if name in needed and value is None:
            raise InputError(name, f"the scene's {_needer(name)} term needs it", f"set {name}")
        if name not in needed and value is not None:
            raise InputError(
                name,
                f"the scene has no {_needer(name)} term",
                f"remove {name}, or add the {_needer(name)} term to the scene",
            )
    changes = {}
    for name in needed:
        value = np.asarray(getattr(params, name), dtype=float)
        _check_finite(name, value)
        per = PARAMETER_INFO[name][2]
        allowed = {(): "a scalar"}
        if name == "gravity":
            allowed = {(3,): "a 3-vector"}
        elif per == "spring":
            allowed[(model.spring_count,)] = f"one value per spring ({model.spring_count})"
        elif per == "particle":
            allowed[(model.particle_count,)] = f"one value per particle ({model.particle_count})"
        if value.shape not in allowed:
            raise InputError(name, f"has shape {value.shape}", f"give {' or '.join(allowed.values())}")
        if name in NON_NEGATIVE and np.any(value < 0):
            raise InputError(name, f"must be >= 0, got {value.min():g}", f"set a non-negative {name}")
        changes[name] = jnp.asarray(value, dtype=float)
    return params.replace(**changes)


def _needer(name: str) -> str:
    for term, names in TERM_PARAMETERS.items():
        if name in names:
            return term
    return name


def _check_finite(name, value):
    if not np.all(np.isfinite(value)):
        raise InputError(name, "contains NaN or infinity", "give finite numbers")


def _mask(name, value, count, default):
    if value is None:
        return np.full(count, default)
    if isinstance(value, bool):
        return np.full(count, value)
    arr = np.asarray(value)
    if arr.dtype == bool:
        if arr.shape != (count,):
            raise InputError(name, f"mask has shape {arr.shape}, expected ({count},)", "give one flag per particle")
        return arr.copy()
    idx = arr.astype(np.int64).reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= count):
        raise InputError(name, f"particle index out of range 0..{count - 1}", "fix the index list")
    mask = np.zeros(count, dtype=bool)
    mask[idx] = True
    return mask
