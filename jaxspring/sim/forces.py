"""Force terms: small pure pieces that a model composes.

Each term has `force(model, params, x, v) -> (N, 3)` [N] and
`energy(model, params, x) -> scalar` [J] (zero for dissipative terms). A model
holds only the terms its scene needs, so the compiled step holds nothing else.
Every term runs under a `jax.named_scope` of its name, so a compiled step can
be inspected for which terms it contains.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..steppers.layout import to_grid

Y_AXIS = 1


def safe_norm(d: jax.Array, keepdims: bool = False, axis: int = -1) -> jax.Array:
    """Euclidean norm over `axis` (default the last) with a finite gradient at zero.

    `jnp.linalg.norm` has a NaN gradient at 0; here the gradient at 0 is 0.

    Args:
        d: vectors, shape (..., 3) (or components along `axis`).
    Returns:
        |d|, shape (...) or (..., 1) with `keepdims`.

    Example:
        >>> jax.grad(lambda d: safe_norm(d))(jnp.zeros(3))  # -> [0, 0, 0]
    """
    squared = jnp.sum(d * d, axis=axis, keepdims=keepdims)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


def safe_direction(d: jax.Array, length: jax.Array) -> jax.Array:
    """d / |d|, and 0 where |d| = 0 (finite value and gradient)."""
    return d / jnp.where(length > 0, length, 1.0)


def _grid_norm(d: jax.Array) -> jax.Array:
    """safe_norm over the component axis 0 of a grid-layout array (3, *shape), keeping it."""
    return safe_norm(d, keepdims=True, axis=0)


def _grid(model, values):
    """Per-particle values (or a scalar) in the grid layout of the model's lattice."""
    return to_grid(model.lattice[0], values)


def per_item(value: jax.Array) -> jax.Array:
    """A scalar parameter as is; a per-spring/per-particle one as a column (K, 1)."""
    return value if jnp.ndim(value) == 0 else value[:, None]


@dataclasses.dataclass(frozen=True)
class Springs:
    """Springs with damping along the spring (docs/physics.md).

    For spring (a, b) with d = x_b - x_a, L = |d|, u = d / L, the force on a is
    f = [ks (L - L0) + kd ((v_b - v_a) . u)] u and on b it is -f.
    Needs params `ks` [N/m] and `kd` [N s/m], scalars or shape (S,).
    """

    name = "springs"

    def spring_vectors(self, model, params, x, v):
        """Per-spring force on particle a, shape (S, 3), and extension L - L0 (S, 1)."""
        a, b = model.springs[:, 0], model.springs[:, 1]
        d = x[b] - x[a]
        length = safe_norm(d, keepdims=True)
        unit = safe_direction(d, length)
        extension = length - model.rest_length[:, None]
        closing_speed = jnp.sum((v[b] - v[a]) * unit, axis=-1, keepdims=True)
        magnitude = (
            per_item(model.per_spring(params.ks)) * extension + per_item(model.per_spring(params.kd)) * closing_speed
        )
        return magnitude * unit, extension

    def force(self, model, params, x, v):
        with jax.named_scope(self.name):
            f, _ = self.spring_vectors(model, params, x, v)
            a, b = model.springs[:, 0], model.springs[:, 1]
            return jnp.zeros_like(x).at[a].add(f).at[b].add(-f)

    def grid_force(self, model, params, x, v):
        """The same force on a lattice in grid layout (3, *shape), one neighbour family at a time.

        For family `offset` the springs join every lattice cell i to i + offset: their
        vectors are a difference of two shifted views of the positions, and their forces
        go back by padding (no gather, no scatter), which XLA fuses into a few vectorised
        loops over the lattice's last axis. Per-spring ks, kd and rest lengths are
        contiguous slices of the spring arrays, because families are stored in order.
        """
        with jax.named_scope(self.name):
            shape, offsets = model.lattice
            ks, kd = model.per_spring(params.ks), model.per_spring(params.kd)
            total = jnp.zeros_like(x)
            start = 0
            for offset in offsets:
                lo = tuple(max(0, -o) for o in offset)
                hi = tuple(max(0, o) for o in offset)
                region = tuple(n - abs(o) for n, o in zip(shape, offset))
                src = (slice(None),) + tuple(slice(a, n - b) for a, b, n in zip(lo, hi, shape))
                dst = (slice(None),) + tuple(slice(b, n - a) for a, b, n in zip(lo, hi, shape))
                count = int(np.prod(region))

                def per_family(value, start=start, count=count, region=region):
                    if jnp.ndim(value) == 0:
                        return value
                    return value[start : start + count].reshape((1,) + region)

                d = x[dst] - x[src]
                length = _grid_norm(d)
                unit = safe_direction(d, length)
                extension = length - per_family(model.rest_length)
                closing = jnp.sum((v[dst] - v[src]) * unit, axis=0, keepdims=True)
                f = (per_family(ks) * extension + per_family(kd) * closing) * unit
                total = total + jnp.pad(f, [(0, 0)] + list(zip(lo, hi))) - jnp.pad(f, [(0, 0)] + list(zip(hi, lo)))
                start += count
            return total

    def energy(self, model, params, x):
        with jax.named_scope(self.name):
            a, b = model.springs[:, 0], model.springs[:, 1]
            length = safe_norm(x[b] - x[a])
            return 0.5 * jnp.sum(model.per_spring(params.ks) * (length - model.rest_length) ** 2)


@dataclasses.dataclass(frozen=True)
class Drag:
    """Quadratic air resistance f = -cd |v| v on particles whose drag flag is set.

    Needs param `cd` [N s^2/m^2], scalar or shape (N,).
    """

    name = "drag"

    def force(self, model, params, x, v):
        with jax.named_scope(self.name):
            coefficient = per_item(params.cd) * model.drag[:, None]
            return -coefficient * safe_norm(v, keepdims=True) * v

    def grid_force(self, model, params, x, v):
        with jax.named_scope(self.name):
            coefficient = _grid(model, params.cd) * _grid(model, model.drag)
            return -coefficient * _grid_norm(v) * v

    def energy(self, model, params, x):
        return jnp.zeros((), x.dtype)


@dataclasses.dataclass(frozen=True)
class Gravity:
    """Weight f = m g. Needs param `gravity` [m/s^2], shape (3,)."""

    name = "gravity"

    def force(self, model, params, x, v):
        with jax.named_scope(self.name):
            return model.mass[:, None] * params.gravity[None, :]

    def grid_force(self, model, params, x, v):
        with jax.named_scope(self.name):
            weight = _grid(model, model.mass) * params.gravity.reshape((3,) + (1,) * (x.ndim - 1))
            return jnp.broadcast_to(weight, x.shape)

    def energy(self, model, params, x):
        with jax.named_scope(self.name):
            return -jnp.sum(model.mass * (x @ params.gravity))


@dataclasses.dataclass(frozen=True)
class Ground:
    """Penalty ground plane y = h: below it, f = [kg (h - y) - kgd v_y] y_hat.

    A temporary zero-rest-length spring to the particle's projection on the
    plane. Needs params `kg` [N/m], `kgd` [N s/m] and `ground_height` [m].
    """

    name = "ground"

    def force(self, model, params, x, v):
        with jax.named_scope(self.name):
            depth = params.ground_height - x[:, Y_AXIS]
            normal_force = jnp.where(depth > 0, params.kg * depth - params.kgd * v[:, Y_AXIS], 0.0)
            up = jnp.zeros(3, x.dtype).at[Y_AXIS].set(1.0)
            return normal_force[:, None] * up[None, :]

    def grid_force(self, model, params, x, v):
        with jax.named_scope(self.name):
            depth = params.ground_height - x[Y_AXIS]
            kg, kgd = (_grid(model, p) for p in (params.kg, params.kgd))
            kg, kgd = (p[0] if jnp.ndim(p) else p for p in (kg, kgd))
            normal_force = jnp.where(depth > 0, kg * depth - kgd * v[Y_AXIS], 0.0)
            zero = jnp.zeros_like(normal_force)
            return jnp.stack([normal_force if axis == Y_AXIS else zero for axis in range(3)])

    def energy(self, model, params, x):
        with jax.named_scope(self.name):
            depth = jnp.maximum(params.ground_height - x[:, Y_AXIS], 0.0)
            return 0.5 * jnp.sum(params.kg * depth**2)


def bend_curvature(x: jax.Array, bends: jax.Array) -> jax.Array:
    """Discrete curvature binormal of every bend triple (a, b, c), shape (B, 3).

    With e1 = x_b - x_a and e2 = x_c - x_b, kappa = 2 e1 x e2 / (|e1| |e2| + e1 . e2): it is
    normal to the plane of the bend and |kappa| = 2 tan(theta / 2) for the turning angle
    theta at b (about theta for small bends; the bend's curvature times its length). A
    degenerate triple (a zero-length edge, or folded straight back) has kappa = 0.
    """
    return _bend_geometry(x, bends)[2]


def _bend_geometry(x, bends):
    """Per triple: e1, e2, kappa, 2 / D and the gradients of D = |e1| |e2| + e1 . e2 by e1 and e2."""
    a, b, c = bends[:, 0], bends[:, 1], bends[:, 2]
    e1, e2 = x[b] - x[a], x[c] - x[b]
    n1, n2 = safe_norm(e1, keepdims=True), safe_norm(e2, keepdims=True)
    denominator = n1 * n2 + jnp.sum(e1 * e2, axis=-1, keepdims=True)
    usable = (denominator > 0) & (n1 > 0) & (n2 > 0)
    two_over = jnp.where(usable, 2.0 / jnp.where(usable, denominator, 1.0), 0.0)
    ratio = jnp.where(usable, n2 / jnp.where(usable, n1, 1.0), 0.0)  # |e2| / |e1|
    d1 = ratio * e1 + e2  # dD / de1
    d2 = jnp.where(usable, 1.0 / jnp.where(usable, ratio, 1.0), 0.0) * e2 + e1  # dD / de2
    return e1, e2, two_over * jnp.cross(e1, e2), two_over, d1, d2


@dataclasses.dataclass(frozen=True)
class Bending:
    """Bending of a chain at its bend triples (a, b, c), with bending damping (docs/physics.md).

    With kappa the curvature binormal of the triple (`bend_curvature`), kappa_0 its rest
    value `model.rest_curvature` (a magnitude: the rest bend's direction is free) and l the
    triple's length `model.bend_length` (the mean of its two edges at rest), the energy is
    E = kb / (2 l) (|kappa| - kappa_0)^2, a rod of bending stiffness EI = kb, and the
    damping force is the Rayleigh one on the rate of the same strain,
    f = -kbd / l (d|kappa|/dt) grad |kappa| (a rigid motion feels none). Needs params
    `kb` [N m^2] and `kbd` [N m^2 s], scalars or shape (B,).
    """

    name = "bending"

    def force(self, model, params, x, v):
        with jax.named_scope(self.name):
            # kappa = 2 w / D, w = e1 x e2: for a cotangent c, d(c . kappa) = (2 / D) [de1 . (e2 x c)
            # + de2 . (c x e1)] - (c . kappa / D) dD; the force is f = -J^T c (J = d kappa / dx) with
            # c = kb / l (kappa - kappa_0 u) + kbd / l (u . J v) u, u = kappa / |kappa| (0 at 0)
            e1, e2, kappa, two_over, d1, d2 = _bend_geometry(x, model.bends)
            a, b, c = model.bends[:, 0], model.bends[:, 1], model.bends[:, 2]
            u1, u2 = v[b] - v[a], v[c] - v[b]
            rate = two_over * (jnp.cross(u1, e2) + jnp.cross(e1, u2))
            rate = rate - 0.5 * two_over * kappa * (
                jnp.sum(d1 * u1, -1, keepdims=True) + jnp.sum(d2 * u2, -1, keepdims=True)
            )
            size = safe_norm(kappa, keepdims=True)
            nonzero = size > 0
            unit = kappa * jnp.where(nonzero, 1.0 / jnp.where(nonzero, size, 1.0), 0.0)
            kb = jnp.asarray(params.kb)[..., None] / model.bend_length[:, None]
            kbd = jnp.asarray(params.kbd)[..., None] / model.bend_length[:, None]
            along = jnp.sum(unit * rate, axis=-1, keepdims=True)
            cot = kb * (kappa - model.rest_curvature[:, None] * unit) + kbd * along * unit
            scale = 0.5 * two_over * jnp.sum(cot * kappa, axis=-1, keepdims=True)
            g1 = two_over * jnp.cross(e2, cot) - scale * d1  # d(c . kappa) / de1
            g2 = two_over * jnp.cross(cot, e1) - scale * d2
            force = jnp.zeros_like(x).at[a].add(g1).at[b].add(g2 - g1).at[c].add(-g2)
            return force

    def energy(self, model, params, x):
        with jax.named_scope(self.name):
            kappa = bend_curvature(x, model.bends)
            # (|kappa| - kappa_0)^2 expanded: where kappa_0 = 0 it is |kappa|^2, smooth through a
            # straight triple, so the force's linearisation there (stability, Gauss-Newton) is right
            k0 = model.rest_curvature
            strain = jnp.sum(kappa**2, axis=-1) - 2.0 * k0 * safe_norm(kappa) + k0**2
            return 0.5 * jnp.sum(jnp.asarray(params.kb) / model.bend_length * strain)


# Which parameters each term reads; used to validate a Params against a Model.
TERM_PARAMETERS = {
    "springs": ("ks", "kd"),
    "drag": ("cd",),
    "gravity": ("gravity",),
    "ground": ("kg", "kgd", "ground_height"),
    "bending": ("kb", "kbd"),
}
TERMS = {term.name: term for term in (Springs(), Drag(), Gravity(), Ground(), Bending())}


def register_term(term, parameters: tuple = ()) -> None:
    """Make a force term available to models by its name (`model.replace(terms=... + (name,))`).

    A term is a hashable object with `name`, `force(model, params, x, v) -> (N, 3)` [N]
    and `energy(model, params, x) -> scalar` [J]; with `grid_force(model, params, x, v)`
    in grid layout (3, *shape) the grid steppers run it too. `parameters` names the
    `Params` fields it reads. Steppers that do not run it refuse models that use it. A
    force reads neither `model.dt` nor `model.integrator` (the stability analyser
    linearises it once for every time step and integrator).

    Example:
        >>> register_term(LinearDrag(), parameters=("cd",))
    """
    known = TERMS.get(term.name)
    if known is not None and known != term:
        raise ValueError(f"a different force term is already registered as {term.name!r}")
    TERMS[term.name] = term
    TERM_PARAMETERS[term.name] = tuple(parameters)
