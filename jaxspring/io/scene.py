"""Scenes: a model, its params and an initial state, loaded from TOML files."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..sim.model import check_params, make_model
from ..sim.params import Params
from ..sim.scene import Scene
from ..sim.state import State
from ..sim.topology import NEIGHBOUR_SETS, lattice_faces, lattice_positions, lattice_springs

AXES = {"x": 0, "y": 1, "z": 2}
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)


def builtin_scene_dir() -> Path:
    """Folder of the built-in scenes (installed copy, else the source checkout's scenes/)."""
    here = Path(__file__).resolve().parent.parent  # the jaxspring package
    for candidate in (here / "scenes", here.parent / "scenes"):
        if candidate.is_dir():
            return candidate
    return here / "scenes"


def builtin_scenes() -> list[str]:
    """Names of the four seed scenes shipped with jaxspring."""
    return ["mass_spring", "chain", "jelly", "cloth"]


def resolve_scene_path(path_or_name) -> Path:
    path = Path(path_or_name)
    if path.exists():
        return path
    candidate = builtin_scene_dir() / f"{path_or_name}.toml"
    if not path.suffix and candidate.exists():
        return candidate
    raise InputError(
        "scene",
        f"file {str(path_or_name)!r} not found",
        f"give a path to a scene TOML file or a built-in name ({', '.join(builtin_scenes())}, "
        f"or a hard case: {', '.join(hard_scenes())})",
    )


def hard_scenes() -> list[str]:
    """Names of the hard cases shipped with jaxspring, e.g. "hard/stiff_cloth"."""
    return sorted(f"hard/{p.stem}" for p in (builtin_scene_dir() / "hard").glob("*.toml"))


def load_scene(path_or_name) -> Scene:
    """Load and validate a scene TOML file (or a built-in scene by name).

    Every error names the file, the field and the fix (`InputError`).

    Example:
        >>> scene = js.load_scene("scenes/cloth.toml")
        >>> scene = js.load_scene("jelly")          # built-in by name
    """
    path = resolve_scene_path(path_or_name)
    try:
        with open(path, "rb") as handle:
            document = tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise InputError("toml", f"not valid TOML ({exc})", "fix the syntax", source=str(path)) from None
    except OSError as exc:
        raise InputError("scene", f"cannot read ({exc.strerror})", "check the path", source=str(path)) from None
    try:
        return scene_from_dict(document, default_name=path.stem)
    except InputError as exc:
        raise exc.within(str(path)) from None


def scene_from_dict(document: dict, default_name: str = "scene") -> Scene:
    """Build a Scene from the parsed contents of a scene file (see README, 'Scene files')."""
    top = _Table(document, "")
    name = top.take("name", _string, default=default_name)
    description = top.take("description", _string, default="")
    dt = top.take("dt", _positive, required=True)
    integrator = top.take("integrator", _string, default="semi_implicit_euler")
    backend = top.take("backend", _string, default="auto")
    steps = top.take("steps", _count, default=1000)
    save_every = top.take("save_every", _count, default=10)
    if save_every < 1 or steps % save_every:
        raise InputError("steps", f"{steps} is not a multiple of save_every={save_every}", "make it one")

    physics = top.table("physics", required=True)
    ks = physics.take("ks", _non_negative_values)
    kd = physics.take("kd", _non_negative_values)
    cd = physics.take("cd", _non_negative_values)
    gravity = physics.take("gravity", _vector3, default=DEFAULT_GRAVITY)
    physics.finish()

    ground = top.table("ground")
    ground_values = None
    if ground is not None:
        ground_values = dict(
            ground_height=ground.take("height", _number, required=True),
            kg=ground.take("kg", _non_negative_values, required=True),
            kgd=ground.take("kgd", _non_negative_values, required=True),
        )
        ground.finish()

    lattice = top.table("lattice")
    particles = top.table("particles")
    springs_table = top.table("springs")
    initial = top.table("initial")
    top.finish()
    if (lattice is None) == (particles is None):
        raise InputError(
            "lattice",
            "a scene needs exactly one of [lattice] or [particles]",
            "describe the particles with one of them",
        )
    lattice_shape = None
    if lattice is not None:
        if springs_table is not None:
            raise InputError("springs", "[springs] is only for [particles] scenes", "remove it, or use [particles]")
        topology = _lattice_topology(lattice, has_drag=cd is not None)
        lattice_shape = topology.pop("lattice_shape")
    else:
        topology = _explicit_topology(particles, springs_table, has_drag=cd is not None)

    x = topology.pop("positions")
    v = topology.pop("velocities")
    if initial is not None:
        v = v + np.asarray(initial.take("velocity", _vector3, default=(0.0, 0.0, 0.0)))
        omega = np.asarray(initial.take("angular_velocity", _vector3, default=(0.0, 0.0, 0.0)))
        initial.finish()
        mass = topology["mass"] * np.ones(x.shape[0])
        centre = np.sum(mass[:, None] * x, axis=0) / np.sum(mass)
        v = v + np.cross(omega, x - centre)

    springs = topology["springs"]
    if springs.shape[0] and (ks is None or kd is None):
        missing = "physics.ks" if ks is None else "physics.kd"
        raise InputError(missing, "missing: the scene has springs", f"set {missing.split('.')[1]}")
    if cd is not None and not np.any(topology["drag"]):
        raise InputError("physics.cd", "set but no particle has drag", "remove cd, or set drag = true")
    gravity_on = any(g != 0.0 for g in gravity)
    try:
        model = make_model(
            springs,
            topology["mass"],
            rest_length=topology["rest_length"],
            positions=x,
            pinned=topology["pinned"],
            drag=topology["drag"],
            gravity=gravity_on,
            ground=ground_values is not None,
            integrator=integrator,
            dt=dt,
            lattice_shape=lattice_shape,
            backend=backend,
        )
    except InputError as exc:  # name the table the bad value came from
        table = "lattice" if lattice is not None else "particles"
        prefix = {"springs": "springs", "rest_length": "springs"}.get(exc.field, table)
        raise exc.within("", "" if exc.field in ("dt", "integrator", "backend") else prefix) from None
    values = dict(ks=ks, kd=kd, cd=cd, gravity=gravity if gravity_on else None)
    values.update(ground_values or {})
    params = check_params(model, Params(**{k: _array(v) for k, v in values.items() if v is not None}))
    v = np.where(np.asarray(model.pinned)[:, None], 0.0, v)
    state = State(x=jnp.asarray(x, dtype=float), v=jnp.asarray(v, dtype=float))
    return Scene(
        name=name,
        model=model,
        params=params,
        state=state,
        faces=topology["faces"],
        steps=steps,
        save_every=save_every,
        lattice_shape=lattice_shape,
        description=description,
    )


def _lattice_topology(table: _Table, has_drag: bool) -> dict:
    shape = table.take("shape", _shape, required=True)
    spacing = table.take("spacing", _positive, default=1.0)
    origin = table.take("origin", _vector3, default=(0.0, 0.0, 0.0))
    axes_names = table.take("axes", _string_list, default=["x", "y", "z"][: len(shape)])
    if (
        len(axes_names) != len(shape)
        or any(a not in AXES for a in axes_names)
        or len(set(axes_names)) != len(axes_names)
    ):
        raise InputError(
            "axes",
            f"{axes_names} does not map the {len(shape)} lattice axes",
            'give distinct names from "x", "y", "z", one per axis',
        )
    sets = table.take("springs", _string_list, required=True)
    for name in sets:
        if name not in NEIGHBOUR_SETS:
            raise InputError("springs", f"unknown neighbour set {name!r}", f"use some of {', '.join(NEIGHBOUR_SETS)}")
    pinned_cells = table.take("pinned", _index_lists, default=[])
    mass = table.take("mass", _positive, default=1.0)
    drag = table.take("drag", _boolean, default=has_drag)
    table.finish()
    positions = lattice_positions(shape, spacing, origin, [AXES[a] for a in axes_names])
    pinned = []
    for cell in pinned_cells:
        if len(cell) != len(shape) or any(not 0 <= c < n for c, n in zip(cell, shape)):
            raise InputError("pinned", f"lattice index {cell} is outside the shape {list(shape)}", "fix the index")
        pinned.append(int(np.ravel_multi_index(tuple(cell), shape)))
    count = positions.shape[0]
    return dict(
        positions=positions,
        velocities=np.zeros_like(positions),
        springs=lattice_springs(shape, sets),
        rest_length=None,
        mass=float(mass),
        pinned=pinned,
        drag=np.full(count, bool(drag)),
        faces=lattice_faces(shape),
        lattice_shape=tuple(shape),
    )


def _explicit_topology(particles: _Table, springs_table: _Table | None, has_drag: bool) -> dict:
    positions = np.asarray(particles.take("x", _vectors, required=True), dtype=float)
    count = positions.shape[0]
    velocities = particles.take("v", _vectors, default=None)
    velocities = np.zeros_like(positions) if velocities is None else np.asarray(velocities, dtype=float)
    if velocities.shape != positions.shape:
        raise InputError("v", f"has {velocities.shape[0]} velocities for {count} particles", "give one per particle")
    mass = particles.take("mass", _positive_values, default=1.0)
    mass = (
        np.broadcast_to(np.asarray(mass, dtype=float), (count,)) if np.ndim(mass) == 0 or len(mass) == count else None
    )
    if mass is None:
        raise InputError("mass", f"needs 1 or {count} values", "give one mass per particle or one for all")
    pinned = particles.take("pinned", _index_list, default=[])
    drag = particles.take("drag", _flags, default=has_drag)
    drag = np.broadcast_to(np.asarray(drag, dtype=bool), (count,)) if np.ndim(drag) == 0 or len(drag) == count else None
    if drag is None:
        raise InputError("drag", f"needs 1 or {count} flags", "give one flag per particle or one for all")
    faces = particles.take("faces", _index_triples, default=[])
    particles.finish()
    springs = np.zeros((0, 2), dtype=np.int64)
    rest_length = None
    if springs_table is not None:
        springs = np.asarray(springs_table.take("pairs", _index_pairs, required=True), dtype=np.int64).reshape(-1, 2)
        rest_length = springs_table.take("rest_length", _non_negative_values, default=None)
        if rest_length is not None and np.ndim(rest_length) == 1 and len(rest_length) != springs.shape[0]:
            raise InputError(
                "springs.rest_length",
                f"has {len(rest_length)} values for {springs.shape[0]} springs",
                "give one per spring",
            )
        springs_table.finish()
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= count):
        raise InputError("particles.faces", f"particle index out of range 0..{count - 1}", "fix the triangle list")
    return dict(
        positions=positions,
        velocities=velocities,
        springs=springs,
        rest_length=rest_length,
        mass=mass,
        pinned=pinned,
        drag=drag,
        faces=faces,
    )


def _array(value):
    return jnp.asarray(np.asarray(value, dtype=float), dtype=float)


# ---- a small schema checker: every value checked, every unknown key reported ----


class _Table:
    def __init__(self, data: Any, path: str):
        if not isinstance(data, dict):
            raise InputError(path or "scene", "must be a table", f"write it as [{path}]")
        self.data, self.path, self.seen = data, path, set()

    def _field(self, key):
        return f"{self.path}.{key}" if self.path else key

    def take(self, key, check, required=False, default=None):
        self.seen.add(key)
        if key not in self.data:
            if required:
                raise InputError(self._field(key), "missing", f"add {key} = ...")
            return default
        try:
            return check(self.data[key])
        except _Bad as bad:
            got = repr(self.data[key])
            got = got if len(got) <= 60 else got[:57] + "..."
            raise InputError(self._field(key), f"{bad.problem}, got {got}", bad.fix) from None

    def table(self, key, required=False):
        self.seen.add(key)
        if key not in self.data:
            if required:
                raise InputError(self._field(key), "missing table", f"add a [{self._field(key)}] table")
            return None
        return _Table(self.data[key], self._field(key))

    def finish(self):
        unknown = sorted(set(self.data) - self.seen)
        if unknown:
            known = ", ".join(sorted(self.seen))
            raise InputError(self._field(unknown[0]), "unknown key", f"remove it or use one of: {known}")


class _Bad(Exception):
    def __init__(self, problem, fix):
        self.problem, self.fix = problem, fix


def _string(value):
    if not isinstance(value, str):
        raise _Bad("must be a string", 'quote it: "..."')
    return value


def _boolean(value):
    if not isinstance(value, bool):
        raise _Bad("must be true or false", "write true or false")
    return value


def _flags(value):
    if isinstance(value, bool):
        return value
    if isinstance(value, list) and all(isinstance(v, bool) for v in value):
        return value
    raise _Bad("must be true/false or a list of them", "write true, false or [true, false, ...]")


def _number(value):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Bad("must be a number", "write a number")
    if not math.isfinite(value):
        raise _Bad("must be finite (no NaN or inf)", "write a finite number")
    return float(value)


def _positive(value):
    value = _number(value)
    if value <= 0:
        raise _Bad("must be > 0", "give a positive number")
    return value


def _count(value):
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise _Bad("must be a non-negative integer", "write a whole number")
    return value


def _values(value, check):
    if isinstance(value, list):
        if not value:
            raise _Bad("must not be empty", "give a number or a non-empty list")
        return [check(v) for v in value]
    return check(value)


def _non_negative_values(value):
    def check(v):
        v = _number(v)
        if v < 0:
            raise _Bad("must be >= 0", "give a non-negative value")
        return v

    return _values(value, check)


def _positive_values(value):
    return _values(value, _positive)


def _vector3(value):
    if not isinstance(value, list) or len(value) != 3:
        raise _Bad("must be a list of 3 numbers", "write [x, y, z]")
    return tuple(_number(v) for v in value)


def _vectors(value):
    if not isinstance(value, list) or not value:
        raise _Bad("must be a non-empty list of [x, y, z]", "write [[x, y, z], ...]")
    return [_vector3(v) for v in value]


def _index(value):
    if isinstance(value, bool) or not isinstance(value, int):
        raise _Bad("must hold integer indices", "write whole numbers")
    return value


def _index_list(value):
    if not isinstance(value, list):
        raise _Bad("must be a list of particle indices", "write [i, j, ...]")
    return [_index(v) for v in value]


def _index_lists(value):
    if not isinstance(value, list):
        raise _Bad("must be a list of lattice indices", "write [[i, j], ...]")
    return [_index_list(v) for v in value]


def _tuples(value, size, what):
    if not isinstance(value, list) or any(not isinstance(v, list) or len(v) != size for v in value):
        raise _Bad(f"must be a list of {what}", f"write [[{', '.join('abc'[:size])}], ...]")
    return [[_index(i) for i in v] for v in value]


def _index_pairs(value):
    return _tuples(value, 2, "index pairs")


def _index_triples(value):
    return _tuples(value, 3, "index triples")


def _shape(value):
    if not isinstance(value, list) or not 1 <= len(value) <= 3:
        raise _Bad("must be a list of 1 to 3 counts", "write e.g. [31, 41]")
    counts = [_index(v) for v in value]
    if any(c < 1 for c in counts):
        raise _Bad("counts must be >= 1", "give positive counts")
    return tuple(counts)


def _string_list(value):
    if not isinstance(value, list):
        raise _Bad("must be a list of strings", 'write ["a", "b"]')
    return [_string(v) for v in value]
