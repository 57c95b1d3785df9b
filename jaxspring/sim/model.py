"""The static structure of a scene: topology, force terms, integrator, dt."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..steppers import Stepper, check_backend, select_stepper
from .checks import check_finite, check_groups, flag_mask, particle_indices
from .forces import TERM_PARAMETERS, TERMS, bend_curvature, safe_norm
from .integrators import Integrator, SemiImplicitEuler, as_integrator
from .params import PER_GROUP, Params, split_name
from .state import State


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Model:
    """Topology (arrays) plus which force terms, integrator, dt and stepper (static).

    Attributes:
        springs: particle index pairs (a, b), int32, shape (S, 2).
        rest_length: spring rest lengths L0 [m], shape (S,).
        mass: particle masses [kg], shape (N,).
        pinned: particles that never move, bool, shape (N,).
        drag: particles that feel air resistance, bool, shape (N,).
        bends: bend triples (a, b, c), the chain bending at b, int32, shape (B, 3) (None: none).
        bend_length: each triple's length l, the mean of its two edges at rest [m], shape (B,).
        rest_curvature: each triple's rest |kappa| (see `forces.bend_curvature`), shape (B,).
        terms: names of the force terms, e.g. ("springs", "gravity") (static; see `TERMS`).
        integrator: the time integrator, an `Integrator` such as `SemiImplicitEuler()`
            (static; a name from `INTEGRATORS` is turned into its default instance).
        dt: time step [s] (static).
        lattice: (shape, offsets) when the springs are whole lattice neighbour families
            in `lattice_springs` order (static); grid steppers then run the springs as
            array shifts instead of scatters (same numbers). None otherwise.
        spring_groups: ((name, count), ...) (static): the springs in order, as named groups
            whose ks and kd may differ (`Params.ks = {name: value}`); () is one unnamed group.
        backend: "auto" (default), "jax" or "native": which steppers may run it (static;
            see `jaxspring.steppers.select_stepper`).
        stepper: how its steps run (static), chosen from the backend when the model is
            built or changed; give one to insist on it (refused if it cannot run the model).

    Build one with `make_model`; a loaded scene carries one as `scene.model`.
    """

    springs: jax.Array
    rest_length: jax.Array
    mass: jax.Array
    pinned: jax.Array
    drag: jax.Array
    bends: jax.Array | None = None
    bend_length: jax.Array | None = None
    rest_curvature: jax.Array | None = None
    terms: tuple = dataclasses.field(metadata=dict(static=True), default=())
    integrator: Integrator = dataclasses.field(metadata=dict(static=True), default=SemiImplicitEuler())
    dt: float = dataclasses.field(metadata=dict(static=True), default=1e-3)
    lattice: tuple | None = dataclasses.field(metadata=dict(static=True), default=None)
    spring_groups: tuple = dataclasses.field(metadata=dict(static=True), default=())
    backend: str = dataclasses.field(metadata=dict(static=True), default="auto")
    stepper: Stepper | None = dataclasses.field(metadata=dict(static=True), default=None)

    def __post_init__(self):
        if not isinstance(self.integrator, Integrator):
            object.__setattr__(self, "integrator", as_integrator(self.integrator))
        for name in self.terms:
            if name not in TERMS:
                raise InputError("terms", f"unknown force term {name!r}", "register it with `register_term` first")
        if self.stepper is None:
            object.__setattr__(self, "stepper", select_stepper(self))
        elif (reason := self.stepper.refusal(self)) is not None:
            raise InputError("stepper", reason, "choose another stepper, or backend='auto'")

    @property
    def particle_count(self) -> int:
        return int(self.mass.shape[0])

    @property
    def spring_count(self) -> int:
        return int(self.springs.shape[0])

    @property
    def bend_count(self) -> int:
        return 0 if self.bends is None else int(self.bends.shape[0])

    @property
    def force_terms(self) -> tuple:
        """The force term objects, in order (see `TERMS`)."""
        return tuple(TERMS[name] for name in self.terms)

    def has(self, term: str) -> bool:
        return term in self.terms

    @property
    def group_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.spring_groups)

    def per_spring(self, value):
        """A spring parameter as the force reads it: a scalar or (S,) as is; {group: value}
        concatenated in spring order, shape (S,)."""
        if not isinstance(value, dict):
            return value
        parts = [jnp.broadcast_to(jnp.asarray(value[name]), (count,)) for name, count in self.spring_groups]
        return jnp.concatenate(parts) if parts else jnp.zeros((0,))

    def per_group(self, value) -> dict:
        """A spring parameter as {group: value}: a scalar for every group, a (S,) array sliced."""
        if isinstance(value, dict):
            return value
        value, groups, start = jnp.asarray(value), {}, 0
        for name, count in self.spring_groups:
            groups[name] = value if value.ndim == 0 else value[start : start + count]
            start += count
        return groups

    def parameter_values(self, params: Params) -> dict:
        """Every parameter by name, with "ks.<group>" / "kd.<group>" entries for each spring group
        (from a scalar or per-spring value too): what can be fitted, compared or printed."""
        values = params.to_dict()
        for base in PER_GROUP:
            value = getattr(params, base)
            if value is not None and not isinstance(value, dict) and self.spring_groups:
                values.update({f"{base}.{group}": v for group, v in self.per_group(value).items()})
        return values

    def params_with(self, params: Params, values: dict) -> Params:
        """`params.with_values(values)`, turning ks or kd into per-group values first where a
        group's value ("ks.<group>") is given.

        Example:
            >>> model.params_with(params, {"ks.bend": 12.0})
        """
        grouped = {split_name(name)[0] for name in values if split_name(name)[1] is not None}
        unknown = [n for n in values if split_name(n)[1] is not None and split_name(n)[1] not in self.group_names]
        if unknown:
            groups = ", ".join(self.group_names) or "none"
            raise InputError(unknown[0], "names a spring group the scene does not have", f"use one of: {groups}")
        params = params.replace(**{base: self.per_group(getattr(params, base)) for base in grouped})
        return params.with_values(values)

    def forward_mode(self) -> Model:
        """This model on the pure-JAX backend, for jvp/jacfwd (the native steppers are reverse-mode
        only), and pure JAX when its terms are changed. States pass between them in (N, 3)
        layout, as through every rollout.

        Its stepper: the grid stepper for a 1-D or 2-D lattice run natively, the generic one
        otherwise. On a 3-D lattice (13 neighbour families) the grid stepper's forward-mode
        programs compile 5x slower than the generic one's (the jelly's 100-step jacfwd: 12 s
        against 2.3 s) and run only 2.2x faster; a fit takes few Jacobians (the report, a
        polish, block Levenberg-Marquardt's iterations), so compiling decides: a jelly fit with
        its segments' starts fitted ran in 22 s instead of 55 s. On the cloth (2-D) the grid's
        Jacobian runs 2.9x faster and compiles in 4.3 s against 2.4 s, so it stays."""
        if self.stepper.forward_mode:
            return self
        grid = self.stepper.layout == "grid" and len(self.lattice[0]) < 3
        return self.replace(backend="jax", lattice=self.lattice if grid else None)

    def force(self, params: Params, x: jax.Array, v: jax.Array) -> jax.Array:
        """Total force on every particle [N], shape (N, 3)."""
        return self.stepper.force(self, params, x, v)

    def energy(self, params: Params, state: State) -> jax.Array:
        """Total mechanical energy [J]: kinetic plus every term's potential."""
        kinetic = 0.5 * jnp.sum(self.mass[:, None] * state.v**2)
        potential = sum(term.energy(self, params, state.x) for term in self.force_terms)
        return kinetic + potential

    def step(self, params: Params, state: State) -> State:
        """Advance one time step dt with the model's integrator ((N, 3) layout in and out)."""
        stepper = self.stepper
        return stepper.from_internal(self, stepper.step(self, params, stepper.to_internal(self, state)))

    def replace(self, **changes) -> Model:
        """A copy with some fields changed; the stepper is chosen again unless given
        (a change of integrator, terms, lattice or backend may change which one runs it)."""
        if "stepper" not in changes and changes.keys() & {"integrator", "terms", "lattice", "backend"}:
            changes["stepper"] = None
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
    integrator: Integrator | str = "semi_implicit_euler",
    dt: float = 1e-3,
    lattice_shape=None,
    spring_groups=None,
    backend: str = "auto",
    bends=None,
    rest_curvature=None,
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
        integrator: an `Integrator` (e.g. `js.sim.BackwardEuler(newton=js.sim.NewtonSettings(...))`)
            or the name of one in `jaxspring.INTEGRATORS`.
        dt: time step [s].
        lattice_shape: the particles' lattice shape when they form one (C order); if
            the springs are whole neighbour families of it, the structured fast path is used.
        spring_groups: ((name, count), ...) naming consecutive runs of `springs` (their counts
            sum to S); default: one unnamed group. See `Model.spring_groups`.
        backend: "auto" (default: the fastest stepper that runs the model), "jax" (pure JAX,
            needed for forward mode through a rollout) or "native" (the C++ kernels; "jax"
            with a notice if they are not built). See `jaxspring.steppers.select_stepper`.
        bends: bend triples (a, b, c), shape (B, 3): adds the bending term (needs `positions`,
            the rest shape, for each triple's length).
        rest_curvature: each triple's rest |kappa|, shape (B,) or one for all; default: the
            triples' curvature at `positions`.

    Example:
        >>> model = make_model([[0, 1]], mass=[1.0, 1.0], positions=[[0, 0, 0], [0, -1, 0]],
        ...                    pinned=[0], dt=1e-3)
    """
    if positions is not None:
        positions = np.asarray(positions, dtype=float)
    mass_np = np.asarray(mass, dtype=float)
    if mass_np.ndim == 0:
        if positions is None:
            raise InputError("mass", "a scalar mass needs `positions` to know N", "pass one mass per particle")
        mass_np = np.full(positions.shape[0], float(mass_np))
    count = mass_np.shape[0]
    check_finite("mass", mass_np)
    if np.any(mass_np <= 0):
        raise InputError("mass", f"must be > 0, got {mass_np.min():g}", "give every particle a positive mass")
    springs_np = particle_indices("springs", springs, count, "fix the spring's endpoints", shape=(-1, 2))
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
    check_finite("rest_length", rest_np)
    if np.any(rest_np < 0):
        raise InputError("rest_length", "must be >= 0", "give non-negative rest lengths")
    pinned_np = flag_mask("pinned", pinned, count, default=False)
    drag_np = flag_mask("drag", drag, count, default=False)
    integrator = as_integrator(integrator)
    if not (np.isfinite(dt) and dt > 0):
        raise InputError("dt", f"must be a finite number > 0, got {dt}", "set a positive time step")
    bend_arrays = _bend_arrays(bends, rest_curvature, positions, count)
    terms = []
    if springs_np.shape[0]:
        terms.append("springs")
    if bend_arrays:
        terms.append("bending")
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
        spring_groups=check_groups(spring_groups, springs_np.shape[0]),
        backend=check_backend(backend),
        **bend_arrays,
    )


def _bend_arrays(bends, rest_curvature, positions, count: int) -> dict:
    """The bending fields of a Model (empty without bend triples), checked."""
    if bends is None or np.size(bends) == 0:
        if rest_curvature is not None:
            raise InputError("rest_curvature", "given without bend triples", "give `bends` too, or remove it")
        return {}
    triples = particle_indices("bends", bends, count, "fix the bend triple's particles", shape=(-1, 3))
    repeats = (triples[:, 0] == triples[:, 1]) | (triples[:, 1] == triples[:, 2]) | (triples[:, 0] == triples[:, 2])
    if repeats.any():
        i = int(np.argmax(repeats))
        raise InputError("bends", f"triple {i} repeats a particle", "give three different particles")
    if positions is None:
        raise InputError("bends", "needs the rest positions for the triples' lengths", "pass `positions`")
    e1 = positions[triples[:, 1]] - positions[triples[:, 0]]
    e2 = positions[triples[:, 2]] - positions[triples[:, 1]]
    length = 0.5 * (np.linalg.norm(e1, axis=-1) + np.linalg.norm(e2, axis=-1))
    if np.any(length <= 0):
        i = int(np.argmin(length))
        raise InputError("bends", f"triple {i} has zero length at rest", "move its particles apart")
    if rest_curvature is None:
        curvature = np.asarray(safe_norm(bend_curvature(jnp.asarray(positions), jnp.asarray(triples))))
    else:
        curvature = np.broadcast_to(np.asarray(rest_curvature, dtype=float), (triples.shape[0],)).copy()
    check_finite("rest_curvature", curvature)
    if np.any(curvature < 0):
        raise InputError("rest_curvature", "must be >= 0 (it is a magnitude)", "give non-negative values")
    return dict(
        bends=jnp.asarray(triples, dtype=jnp.int32),
        bend_length=jnp.asarray(length, dtype=float),
        rest_curvature=jnp.asarray(curvature, dtype=float),
    )


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
