"""Native CPU spring kernel (C++ through `jax.ffi`), forward and reverse mode.

`jaxspring/native/springs.cc` is compiled by the package build into
`jaxspring/_native_springs*.so` (an optional extension: if it cannot be built the
install still succeeds). It computes the spring forces of any topology in one pass
over the springs, and the exact reverse-mode derivative in another; `spring_force`
wraps them in a `jax.custom_vjp`. Being a custom VJP, it supports reverse mode
(`grad`, `vjp`) and `vmap`, but not forward mode (`jvp`, `jacfwd`): models with
backend "native" fall back to the pure-JAX force where jaxspring itself needs forward
mode (backward Euler's Newton solve, the stability analyser, Gauss-Newton in fitting).

Backward formulas, per spring, with cf = ct_a - ct_b (the force's cotangent):
    uc = u . cf;   ct_c = kd uc;   ct_u = m cf + dv ct_c
    ct_L = ks uc - (u . ct_u) / L;  ct_d = ct_u / L + u ct_L;  ct_dv = u ct_c
    ct_ks = e uc,  ct_kd = c uc,  ct_L0 = -ks uc
"""

from __future__ import annotations

import ctypes
import functools
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

_TARGETS = {
    jnp.dtype("float32"): ("jaxspring_springs_f32", "jaxspring_springs_backward_f32"),
    jnp.dtype("float64"): ("jaxspring_springs_f64", "jaxspring_springs_backward_f64"),
}
_SYMBOLS = {
    "jaxspring_springs_f32": "JaxspringSpringsF32",
    "jaxspring_springs_f64": "JaxspringSpringsF64",
    "jaxspring_springs_backward_f32": "JaxspringSpringsBackwardF32",
    "jaxspring_springs_backward_f64": "JaxspringSpringsBackwardF64",
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
