"""Validation of what a user gives a model: parameter values, masks, spring groups.

Each failure is an `InputError` naming the field and the fix (one line).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from .forces import TERM_PARAMETERS
from .params import NON_NEGATIVE, PARAMETER_INFO, PER_GROUP, Params


def check_params(model, params: Params) -> Params:
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
        value = getattr(params, name)
        if isinstance(value, dict):
            changes[name] = _check_group_values(model, name, value)
        else:
            changes[name] = _check_value(model, name, value, PARAMETER_INFO[name][2])
    return params.replace(**changes)


def _check_value(model, name: str, value, per, count=None):
    """One parameter value checked (numeric, finite, shape, sign) and cast to the default float dtype."""
    try:
        value = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        got = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        raise InputError(
            name, f"must be a number or an array of numbers, got {got}", f"give a numeric {name}"
        ) from None
    check_finite(name, value)
    allowed = {(): "a scalar"}
    if name == "gravity":
        allowed = {(3,): "a 3-vector"}
    elif per == "spring":
        count = model.spring_count if count is None else count
        allowed[(count,)] = f"one value per spring ({count})"
    elif per == "bend":
        allowed[(model.bend_count,)] = f"one value per bend triple ({model.bend_count})"
    elif per == "particle":
        allowed[(model.particle_count,)] = f"one value per particle ({model.particle_count})"
    if value.shape not in allowed:
        raise InputError(name, f"has shape {value.shape}", f"give {' or '.join(allowed.values())}")
    if name.partition(".")[0] in NON_NEGATIVE and np.any(value < 0):
        raise InputError(name, f"must be >= 0, got {value.min():g}", f"set a non-negative {name}")
    out = jnp.asarray(value, dtype=float)
    check_representable(name, value, out.dtype)
    return out


def check_representable(name, value, dtype) -> None:
    """Refuse a finite number that overflows `dtype` (1e308 in float32) in one line naming it,
    rather than as an infinity later."""
    try:
        value = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return  # not numbers: the value checks say so
    largest = float(np.finfo(np.dtype(dtype)).max)
    big = np.abs(value[np.isfinite(value)])
    if big.size and big.max() > largest:
        raise InputError(
            name,
            f"{float(big.max()):g} overflows {np.dtype(dtype)} (largest {largest:.3g})",
            "run in float64 (--dtype float64) or give a smaller value",
        )


def _check_group_values(model, name: str, values: dict) -> dict:
    """{group: value} for ks or kd: exactly the model's groups, each a scalar or one value per spring of it."""
    groups = dict(model.spring_groups)
    if name not in PER_GROUP or not groups:
        raise InputError(name, "is given per spring group but the scene has no named groups", f"give one {name}")
    missing, unknown = [g for g in groups if g not in values], [g for g in values if g not in groups]
    if unknown:
        raise InputError(
            f"{name}.{unknown[0]}", "names a spring group the scene does not have", f"use {', '.join(groups)}"
        )
    if missing:
        raise InputError(
            name, f"has no value for the group {missing[0]!r}", f"give every group a {name}, or one for all"
        )
    return {g: _check_value(model, f"{name}.{g}", values[g], "spring", groups[g]) for g in groups}


def check_groups(groups, spring_count: int) -> tuple:
    if not groups:
        return ()
    groups = tuple((str(name), int(count)) for name, count in groups)
    names = [name for name, _ in groups]
    for name in names:
        if not name or "." in name or not name.replace("_", "a").isalnum():
            raise InputError("springs.name", f"{name!r} is not a group name", "use letters, digits and _")
    if len(set(names)) != len(names):
        raise InputError("springs.name", "two spring groups share a name", "give each [[springs]] table its own name")
    if sum(count for _, count in groups) != spring_count:
        raise InputError("spring_groups", f"counts do not add up to {spring_count} springs", "count every spring once")
    return groups


def _needer(name: str) -> str:
    for term, names in TERM_PARAMETERS.items():
        if name in names:
            return term
    return name


def check_finite(name, value):
    if not np.all(np.isfinite(value)):
        raise InputError(name, "contains NaN or infinity", "give finite numbers")


def particle_indices(name, value, count, fix, shape=(-1,)) -> np.ndarray:
    """`value` as int64 particle indices in 0..count-1 (reshaped to `shape`), or a one-line
    InputError naming the problem: non-integers, or the first index out of range, however
    large (Python integers beyond int64 too)."""
    arr = value if isinstance(value, np.ndarray) else np.asarray(value, dtype=object)
    if arr.dtype.kind == "O":
        flat = arr.reshape(-1)
        odd = next((i for i in flat if isinstance(i, bool) or not isinstance(i, (int, np.integer))), None)
        if odd is not None:
            raise InputError(name, f"holds {type(odd).__name__} {odd!r}, not a particle index", fix)
        if any(not -(2**63) <= int(i) < 2**63 for i in flat):
            bad = next(int(i) for i in flat if not -(2**63) <= int(i) < 2**63)
            raise InputError(name, f"particle index {bad} out of range 0..{count - 1}", fix)
        arr = flat.astype(np.int64) if flat.size else np.zeros(0, dtype=np.int64)
    elif arr.dtype.kind == "u":
        if arr.size and arr.max() > 2**62:
            raise InputError(name, f"particle index {int(arr.max())} out of range 0..{count - 1}", fix)
    elif arr.dtype.kind != "i" and arr.size:
        raise InputError(name, f"holds {arr.dtype} values, not particle indices", fix)
    arr = arr.astype(np.int64).reshape(-1)
    outside = (arr < 0) | (arr >= count)
    if outside.any():
        raise InputError(name, f"particle index {int(arr[outside][0])} out of range 0..{count - 1}", fix)
    try:
        return arr.reshape(shape)
    except ValueError:
        raise InputError(name, f"has {arr.size} indices, not rows of {shape[-1]}", fix) from None


def flag_mask(name, value, count, default):
    if value is None:
        return np.full(count, default)
    if isinstance(value, bool):
        return np.full(count, value)
    arr = np.asarray(value)
    if arr.dtype == bool:
        if arr.shape != (count,):
            raise InputError(name, f"mask has shape {arr.shape}, expected ({count},)", "give one flag per particle")
        return arr.copy()
    idx = particle_indices(name, arr, count, "fix the index list")
    mask = np.zeros(count, dtype=bool)
    mask[idx] = True
    return mask


def whole_number(field: str, value) -> int:
    """`value` as an int; an InputError for a bool, a non-number or a number with a fraction.

    Example:
        >>> whole_number("start", 5.0)
        5
    """
    try:
        whole = not isinstance(value, (bool, np.bool_)) and float(value).is_integer()
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise InputError(field, f"must be a whole number, got {value!r}", f"give an integer {field}")
    return int(value)
