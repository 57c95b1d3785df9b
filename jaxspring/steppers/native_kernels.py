"""Native CPU kernels (C++ through `jax.ffi`), forward and reverse mode.

The sources in `jaxspring/steppers/native/` (`springs.cc`, the `lattice_*.cc` files, and the
spring law written once in `spring_law.h`) are compiled by the package build into
`jaxspring/steppers/_native_springs*.so` (an optional extension: if it cannot be built the
install still succeeds). Two kernels, each wrapped in a `jax.custom_vjp` whose
backward is native too:

- `spring_force`: the spring forces of any topology in one pass over the springs,
  and the exact reverse-mode derivative in another (the native springs stepper's force).
- `bending_force`: the bending term's forces at its bend triples, and their reverse-mode
  derivative (`native/bending.cc`: forward-mode dual numbers through the curvature's
  symmetric Hessians).
- `lattice_advance`: whole semi-implicit Euler steps of a lattice scene (below; the native
  lattice stepper's `advance`).

Being custom VJPs they support reverse mode (`grad`, `vjp`) and `vmap`, but not
forward mode (`jvp`, `jacfwd`): the native steppers hand over to their pure-JAX twins
where jaxspring itself needs forward mode (backward Euler's Newton solve, the
stability analyser, Gauss-Newton in fitting; `Model.forward_mode`).

Backward formulas, per spring, with cf = ct_a - ct_b (the force's cotangent):
    uc = u . cf;   ct_c = kd uc;   ct_u = m cf + dv ct_c
    ct_L = ks uc - (u . ct_u) / L;  ct_d = ct_u / L + u ct_L;  ct_dv = u ct_c
    ct_ks = e uc,  ct_kd = c uc,  ct_L0 = -ks uc
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

_TARGETS = {
    jnp.dtype("float32"): ("jaxspring_springs_f32", "jaxspring_springs_backward_f32"),
    jnp.dtype("float64"): ("jaxspring_springs_f64", "jaxspring_springs_backward_f64"),
}
_SYMBOLS = {
    "jaxspring_springs_f32": "JaxspringSpringsF32",
    "jaxspring_springs_f64": "JaxspringSpringsF64",
    "jaxspring_springs_backward_f32": "JaxspringSpringsBackwardF32",
    "jaxspring_springs_backward_f64": "JaxspringSpringsBackwardF64",
    "jaxspring_lattice_f32": "JaxspringLatticeF32",
    "jaxspring_lattice_f64": "JaxspringLatticeF64",
    "jaxspring_lattice_backward_f32": "JaxspringLatticeBackwardF32",
    "jaxspring_lattice_backward_f64": "JaxspringLatticeBackwardF64",
    "jaxspring_bending_f32": "JaxspringBendingF32",
    "jaxspring_bending_f64": "JaxspringBendingF64",
    "jaxspring_bending_backward_f32": "JaxspringBendingBackwardF32",
    "jaxspring_bending_backward_f64": "JaxspringBendingBackwardF64",
}


def library_path() -> Path | None:
    """The compiled kernel library, or None when the build did not produce it."""
    here = Path(__file__).resolve().parent
    found = sorted(here.glob("_native_springs*.so")) + sorted(here.glob("_native_springs*.pyd"))
    return found[0] if found else None


@functools.cache
def available() -> bool:
    """Whether the native kernel is built and registered with XLA (done once)."""
    path = library_path()
    if path is None:
        return False
    try:
        library = ctypes.CDLL(str(path))
        for target, symbol in _SYMBOLS.items():
            jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(library, symbol)), platform="cpu")
    except (OSError, AttributeError):
        return False
    return True


_NOTICED = []


def notice_unavailable():
    """One line on stderr, once per process, when "native" was asked for but is not built."""
    if not _NOTICED:
        _NOTICED.append(True)
        print(
            "jaxspring: notice: the native kernel is not built (reinstall with a C++17 compiler); "
            "using the pure-JAX path",
            file=sys.stderr,
        )


def _forward(x, v, pairs, rest, ks, kd):
    target = _TARGETS[jnp.dtype(x.dtype)][0]
    call = jax.ffi.ffi_call(target, jax.ShapeDtypeStruct(x.shape, x.dtype), vmap_method="sequential")
    return call(x, v, pairs, rest, ks, kd)


def _backward(x, v, pairs, rest, ks, kd, cotangent):
    target = _TARGETS[jnp.dtype(x.dtype)][1]
    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype)] * 2 + [jax.ShapeDtypeStruct(rest.shape, x.dtype)] * 3
    call = jax.ffi.ffi_call(target, shapes, vmap_method="sequential")
    return call(x, v, pairs, rest, ks, kd, cotangent)


@jax.custom_vjp
def _springs(x, v, pairs, rest, ks, kd):
    return _forward(x, v, pairs, rest, ks, kd)


def _springs_fwd(x, v, pairs, rest, ks, kd):
    return _forward(x, v, pairs, rest, ks, kd), (x, v, pairs, rest, ks, kd)


def _springs_bwd(residuals, cotangent):
    x, v, pairs, rest, ks, kd = residuals
    ct_x, ct_v, ct_ks, ct_kd, ct_rest = _backward(x, v, pairs, rest, ks, kd, cotangent)
    if ks.shape[0] != rest.shape[0]:  # one value for every spring
        ct_ks = jnp.sum(ct_ks, keepdims=True)
    if kd.shape[0] != rest.shape[0]:
        ct_kd = jnp.sum(ct_kd, keepdims=True)
    zero_pairs = jnp.zeros(pairs.shape, jax.dtypes.float0)
    return ct_x, ct_v, zero_pairs, ct_rest, ct_ks, ct_kd


_springs.defvjp(_springs_fwd, _springs_bwd)


def spring_force(x, v, pairs, rest, ks, kd):
    """Total spring force (N, 3) on every particle; ks, kd scalars or per spring.

    Example:
        >>> f = spring_force(state.x, state.v, model.springs, model.rest_length, params.ks, params.kd)
    """
    if not available():
        raise RuntimeError("the native kernel is not built; use backend='jax' (make_model checks this for you)")
    dtype = x.dtype
    # a scalar goes in as one value (the kernel reads it for every spring); its
    # gradient is the sum of the per-spring ones the kernel returns
    ks, kd = (jnp.reshape(jnp.asarray(k, dtype), (-1,)) for k in (ks, kd))
    return _springs(x, v.astype(dtype), pairs.astype(jnp.int32), rest.astype(dtype), ks, kd)


def _bending_call(name: str, dtype, shapes, *args):
    target = f"jaxspring_{name}_{'f64' if jnp.dtype(dtype) == jnp.float64 else 'f32'}"
    return jax.ffi.ffi_call(target, shapes, vmap_method="broadcast_all")(*args)


@jax.custom_vjp
def _bending(x, v, bends, length, kappa0, kb, kbd):
    return _bending_call(
        "bending", x.dtype, jax.ShapeDtypeStruct(x.shape, x.dtype), x, v, bends, length, kappa0, kb, kbd
    )


def _bending_fwd(x, v, bends, length, kappa0, kb, kbd):
    return _bending(x, v, bends, length, kappa0, kb, kbd), (x, v, bends, length, kappa0, kb, kbd)


def _bending_bwd(residuals, cotangent):
    x, v, bends, length, kappa0, kb, kbd = residuals
    shapes = [jax.ShapeDtypeStruct(a.shape, x.dtype) for a in (x, x, length, kappa0, kb, kbd)]
    ct = _bending_call("bending_backward", x.dtype, shapes, x, v, bends, length, kappa0, kb, kbd, cotangent)
    ct_x, ct_v, ct_length, ct_kappa0, ct_kb, ct_kbd = ct
    return ct_x, ct_v, jnp.zeros(bends.shape, jax.dtypes.float0), ct_length, ct_kappa0, ct_kb, ct_kbd


_bending.defvjp(_bending_fwd, _bending_bwd)


def bending_force(x, v, bends, length, kappa0, kb, kbd):
    """The bending term's force (N, 3) on every particle (forces.py `Bending`); kb, kbd scalars
    or one per bend triple.

    Example:
        >>> f = bending_force(x, v, model.bends, model.bend_length, model.rest_curvature, params.kb, params.kbd)
    """
    if not available():
        raise RuntimeError("the native kernel is not built; use backend='jax' (make_model checks this for you)")
    dtype = x.dtype
    # a scalar goes in as one value; the kernel sums its per-triple cotangents itself
    kb, kbd = (jnp.reshape(jnp.asarray(k, dtype), (-1,)) for k in (kb, kbd))
    shape = jnp.shape(x)
    f = _bending(x, v.astype(dtype), bends.astype(jnp.int32), length.astype(dtype), kappa0.astype(dtype), kb, kbd)
    return jnp.reshape(f, shape)


# ----------------------------------------------------------------------------------
# Whole steps of a lattice scene (jaxspring/steppers/native/lattice.cc): springs, drag, gravity
# and ground, semi-implicit Euler, `steps` steps in one call. Its VJP is the second
# kernel: the forward call keeps the state every ~sqrt(steps) steps; the backward call
# replays one such segment at a time on a second thread (keeping its states) while the
# first runs the exact reverse pass over the segment before. Memory ~3 sqrt(steps)
# states; time one forward pass plus the reverse pass (the replay runs alongside).
# Scalar ks and kd go in as one value each, and the backward call is told which
# inputs are differentiated (symbolic zeros): it skips the rest lengths' and masses'
# cotangents nobody asked for and sums those of a scalar ks, kd itself.

_DRAG, _GRAVITY, _GROUND = 1, 2, 4

# Test hooks of the lattice kernel, sent with every call as its `test` attribute (zero
# otherwise; read when a call is traced, so a test that sets them clears JAX's caches):
# _TEST_IMPATIENT makes the backward call's first thread give up on the second at its first
# replay and replays the rest alone (as when the second core is slow); _TEST_OUT_OF_MEMORY
# makes the backward call's allocation of replayed states fail (as for a lattice too
# large for memory), which raises an error in Python.
_TEST_IMPATIENT, _TEST_OUT_OF_MEMORY = 1, 2
_test_hooks = 0


def _lattice_inputs(model, params, dtype):
    """The kernel's parameter arrays, one value per spring / particle, in `dtype`; ks and kd
    as one value when they are scalars (the kernel then sums their cotangents itself)."""
    springs, particles = model.spring_count, model.particle_count

    def per(value, count):
        return jnp.broadcast_to(jnp.asarray(value, dtype), (count,))

    def spring_values(value):
        value = jnp.asarray(value, dtype)
        return jnp.reshape(value, (1,)) if value.ndim == 0 else per(value, springs)

    zeros = jnp.zeros((particles,), dtype)
    cdm = per(params.cd, particles) * model.drag.astype(dtype) if model.has("drag") else zeros
    gravity = jnp.asarray(params.gravity, dtype) if model.has("gravity") else jnp.zeros((3,), dtype)
    ground = model.has("ground")
    return (
        model.rest_length.astype(dtype),
        spring_values(model.per_spring(params.ks)),
        spring_values(model.per_spring(params.kd)),
        model.mass.astype(dtype),
        (~model.pinned).astype(dtype),
        cdm,
        gravity,
        per(params.kg, particles) if ground else zeros,
        per(params.kgd, particles) if ground else zeros,
        jnp.reshape(jnp.asarray(params.ground_height, dtype), (1,)) if ground else jnp.zeros((1,), dtype),
    )


def _lattice_config(model, steps):
    shape, offsets = model.lattice
    flags = sum(flag for term, flag in (("drag", _DRAG), ("gravity", _GRAVITY), ("ground", _GROUND)) if model.has(term))
    stride = max(1, math.isqrt(max(int(steps) - 1, 0)) + 1)  # ~sqrt(steps): stored + replayed states
    return (tuple(shape), tuple(o for offset in offsets for o in offset), int(steps), float(model.dt), flags, stride)


def _attributes(config):
    shape, offsets, steps, dt, flags, stride = config
    return dict(
        shape=np.asarray(shape, np.int64),
        offsets=np.asarray(offsets, np.int64),
        steps=np.int64(steps),
        dt=np.float64(dt),
        flags=np.int64(flags),
        stride=np.int64(stride),
        test=np.int64(_test_hooks),
    )


def _lattice_call(config, x, v, inputs, store):
    target = "jaxspring_lattice_f32" if x.dtype == jnp.float32 else "jaxspring_lattice_f64"
    steps, stride = config[2], config[5]
    state = jax.ShapeDtypeStruct(x.shape, x.dtype)
    stored = jax.ShapeDtypeStruct((-(-steps // stride), 2) + x.shape if store else (0,), x.dtype)
    call = jax.ffi.ffi_call(target, (state, state, stored), vmap_method="broadcast_all")
    return call(x, v, *inputs, **_attributes(config))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _advance(config, x, v, *inputs):
    x, v, _ = _lattice_call(config, x, v, inputs, store=False)
    return x, v


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class _Needs:
    """Which parameter inputs are differentiated (bit i: inputs[i]), known when tracing."""

    bits: int


def _advance_fwd(config, x, v, *inputs):
    # symbolic zeros: every argument comes with whether it is differentiated; the
    # backward call then skips the cotangents nobody asked for (rest lengths, masses)
    needs = _Needs(sum(1 << i for i, a in enumerate(inputs) if a.perturbed))
    x, v, inputs = x.value, v.value, tuple(a.value for a in inputs)
    x_end, v_end, states = _lattice_call(config, x, v, inputs, store=True)
    return (x_end, v_end), (states, v_end, inputs, needs)


def _advance_bwd(config, residuals, cotangents):
    states, v_end, inputs, needs = residuals
    dtype = v_end.dtype
    ct_x, ct_v = (
        jnp.zeros(v_end.shape, dtype) if isinstance(c, jax.custom_derivatives.SymbolicZero) else c.astype(dtype)
        for c in cotangents
    )
    target = "jaxspring_lattice_backward_f32" if dtype == jnp.float32 else "jaxspring_lattice_backward_f64"
    shapes = [jax.ShapeDtypeStruct(a.shape, dtype) for a in (v_end, v_end)]
    shapes += [jax.ShapeDtypeStruct(a.shape, dtype) for i, a in enumerate(inputs) if i != 4]  # not `free`
    call = jax.ffi.ffi_call(target, shapes, vmap_method="broadcast_all")
    ct = call(states, v_end, *inputs, ct_x, ct_v, **_attributes(config), needs=np.int64(needs.bits))
    ct_state, ct_inputs = ct[:2], list(ct[2:])
    ct_inputs.insert(4, jnp.zeros_like(inputs[4]))  # the pinned mask is not differentiable
    return (*ct_state, *ct_inputs)


_advance.defvjp(_advance_fwd, _advance_bwd, symbolic_zeros=True)


def lattice_advance(model, params, x, v, steps: int):
    """`steps` steps of a lattice model from grid-layout x, v (3, *shape); returns (x, v).

    Differentiable in reverse mode (params, x, v, and the model's rest lengths and
    masses) and batched under vmap; not forward mode.

    Example:
        >>> x, v = lattice_advance(model, params, x, v, 100)
    """
    if not available():
        raise RuntimeError("the native kernel is not built; use backend='jax' (make_model checks this for you)")
    dtype = x.dtype
    grid_shape = x.shape
    flat = (3, model.particle_count)
    inputs = _lattice_inputs(model, params, dtype)
    x, v = _advance(_lattice_config(model, steps), x.reshape(flat), v.astype(dtype).reshape(flat), *inputs)
    return x.reshape(grid_shape), v.reshape(grid_shape)
