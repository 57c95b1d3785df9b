"""Scenes: a model, its params and an initial state, loaded from TOML files."""

from __future__ import annotations

import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..resources import check_particles
from ..sim.checks import check_params
from ..sim.model import make_model
from ..sim.params import Params
from ..sim.scene import Scene
from ..sim.state import State
from ..sim.topology import NEIGHBOUR_SETS, lattice_faces, lattice_positions, lattice_springs
from . import schema

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
    document = schema.read_toml(path, "scene")
    try:
        return scene_from_dict(document, default_name=path.stem)
    except InputError as exc:
        raise exc.within(str(path)) from None


def scene_from_dict(document: dict, default_name: str = "scene") -> Scene:
    """Build a Scene from the parsed contents of a scene file (see docs/file-formats.md)."""
    top = schema.Table(document, "")
    name = top.take("name", schema.string, default=default_name)
    description = top.take("description", schema.string, default="")
    dt = top.take("dt", schema.positive, required=True)
    integrator = top.take("integrator", schema.string, default="semi_implicit_euler")
    backend = top.take("backend", schema.string, default="auto")
    steps = top.take("steps", schema.count, default=1000)
    save_every = top.take("save_every", schema.count, default=10)
    if save_every < 1 or steps % save_every:
        raise InputError("steps", f"{steps} is not a multiple of save_every={save_every}", "make it one")

    physics = top.table("physics", required=True)
    ks = physics.take("ks", schema.grouped_non_negative_values)
    kd = physics.take("kd", schema.grouped_non_negative_values)
    cd = physics.take("cd", schema.non_negative_values)
    kb = physics.take("kb", schema.non_negative_values)
    kbd = physics.take("kbd", schema.non_negative_values)
    gravity = physics.take("gravity", schema.vector3, default=DEFAULT_GRAVITY)
    physics.finish()

    ground = top.table("ground")
    ground_values = None
    if ground is not None:
        ground_values = dict(
            ground_height=ground.take("height", schema.number, required=True),
            kg=ground.take("kg", schema.non_negative_values, required=True),
            kgd=ground.take("kgd", schema.non_negative_values, required=True),
        )
        ground.finish()

    lattice = top.table("lattice")
    particles = top.table("particles")
    springs_tables = top.tables("springs")
    bending = top.table("bending")
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
        if springs_tables:
            raise InputError("springs", "[springs] is only for [particles] scenes", "remove it, or use [particles]")
        topology = _lattice_topology(lattice, has_drag=cd is not None)
        lattice_shape = topology.pop("lattice_shape")
    else:
        topology = _explicit_topology(particles, springs_tables, has_drag=cd is not None)
    bends, rest_curvature = None, None
    if bending is not None:
        if lattice is not None:
            raise InputError("bending", "[bending] is only for [particles] scenes", "remove it, or use [particles]")
        bends = np.asarray(bending.take("triples", schema.index_triples, required=True), dtype=np.int64).reshape(-1, 3)
        rest_curvature = bending.take("rest_curvature", schema.non_negative_values, default=None)
        if rest_curvature is not None and np.ndim(rest_curvature) == 1 and len(rest_curvature) != bends.shape[0]:
            raise InputError(
                "bending.rest_curvature",
                f"has {len(rest_curvature)} values for {bends.shape[0]} triples",
                "give one per triple or one for all",
            )
        bending.finish()
        if not bends.size:
            raise InputError("bending.triples", "is empty", "list the bend triples, or remove [bending]")
    for key, value in (("kb", kb), ("kbd", kbd)):
        if (value is None) != (bends is None):
            fix = f"set physics.{key}" if value is None else f"remove physics.{key}, or add a [bending] table"
            raise InputError(
                f"physics.{key}", "missing: the scene has [bending]" if value is None else "set without [bending]", fix
            )

    x = topology.pop("positions")
    v = topology.pop("velocities")
    if initial is not None:
        v = v + np.asarray(initial.take("velocity", schema.vector3, default=(0.0, 0.0, 0.0)))
        omega = np.asarray(initial.take("angular_velocity", schema.vector3, default=(0.0, 0.0, 0.0)))
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
            spring_groups=topology["spring_groups"],
            backend=backend,
            bends=bends,
            rest_curvature=rest_curvature,
        )
    except InputError as exc:  # name the table the bad value came from
        table = "lattice" if lattice is not None else "particles"
        if exc.field == "bends":  # the file calls them triples
            exc = InputError("bending.triples", exc.problem, exc.fix)
        prefix = {"springs": "springs", "rest_length": "springs", "rest_curvature": "bending"}.get(exc.field, table)
        raise exc.within("", "" if exc.field in ("dt", "integrator", "backend") else prefix) from None
    values = dict(ks=ks, kd=kd, cd=cd, kb=kb, kbd=kbd, gravity=gravity if gravity_on else None)
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


MIN_SPACING = 1e-9
"""The smallest lattice spacing [m]: below it, rest lengths underflow or round to zero."""


def _lattice_topology(table: schema.Table, has_drag: bool) -> dict:
    shape = table.take("shape", schema.shape, required=True)
    check_particles(math.prod(shape), "lattice.shape")
    spacing = table.take("spacing", schema.positive, default=1.0)
    if spacing < MIN_SPACING:
        raise InputError(
            "spacing",
            f"{spacing:g} m is below {MIN_SPACING:g} m: neighbouring particles would coincide in floating point",
            "give the spacing in metres, e.g. 0.01",
        )
    origin = table.take("origin", schema.vector3, default=(0.0, 0.0, 0.0))
    axes_names = table.take("axes", schema.string_list, default=["x", "y", "z"][: len(shape)])
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
    sets = table.take("springs", schema.string_list, required=True)
    for name in sets:
        if name not in NEIGHBOUR_SETS:
            raise InputError("springs", f"unknown neighbour set {name!r}", f"use some of {', '.join(NEIGHBOUR_SETS)}")
    pinned_cells = table.take("pinned", schema.index_lists, default=[])
    mass = table.take("mass", schema.positive, default=1.0)
    drag = table.take("drag", schema.boolean, default=has_drag)
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
        spring_groups=[(name, lattice_springs(shape, [name]).shape[0]) for name in sets],
        rest_length=None,
        mass=float(mass),
        pinned=pinned,
        drag=np.full(count, bool(drag)),
        faces=lattice_faces(shape),
        lattice_shape=tuple(shape),
    )


def _explicit_topology(particles: schema.Table, springs_tables: list, has_drag: bool) -> dict:
    positions = np.asarray(particles.take("x", schema.vectors, required=True), dtype=float)
    count = positions.shape[0]
    velocities = particles.take("v", schema.vectors, default=None)
    velocities = np.zeros_like(positions) if velocities is None else np.asarray(velocities, dtype=float)
    if velocities.shape != positions.shape:
        raise InputError("v", f"has {velocities.shape[0]} velocities for {count} particles", "give one per particle")
    mass = particles.take("mass", schema.positive_values, default=1.0)
    mass = (
        np.broadcast_to(np.asarray(mass, dtype=float), (count,)) if np.ndim(mass) == 0 or len(mass) == count else None
    )
    if mass is None:
        raise InputError("mass", f"needs 1 or {count} values", "give one mass per particle or one for all")
    pinned = particles.take("pinned", schema.index_list, default=[])
    drag = particles.take("drag", schema.flags, default=has_drag)
    drag = np.broadcast_to(np.asarray(drag, dtype=bool), (count,)) if np.ndim(drag) == 0 or len(drag) == count else None
    if drag is None:
        raise InputError("drag", f"needs 1 or {count} flags", "give one flag per particle or one for all")
    faces = particles.take("faces", schema.index_triples, default=[])
    particles.finish()
    springs, rest_length, groups = _spring_tables(springs_tables)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= count):
        raise InputError("particles.faces", f"particle index out of range 0..{count - 1}", "fix the triangle list")
    return dict(
        positions=positions,
        velocities=velocities,
        springs=springs,
        rest_length=rest_length,
        spring_groups=groups,
        mass=mass,
        pinned=pinned,
        drag=drag,
        faces=faces,
    )


def _spring_tables(tables: list) -> tuple:
    """(pairs (S, 2), rest lengths (S,) or None, groups) from one [springs] table or [[springs]] tables.

    Each [[springs]] table is a named group: `name`, `pairs`, optional `rest_length` (one
    value or one per pair; default: the pairs' initial distances).
    """
    pairs, rests, groups = [], [], []
    named = len(tables) > 1 or any("name" in table.data for table in tables)
    for table in tables:
        name = table.take("name", schema.string, required=named)
        group = np.asarray(table.take("pairs", schema.index_pairs, required=True), dtype=np.int64).reshape(-1, 2)
        rest = table.take("rest_length", schema.non_negative_values, default=None)
        if rest is not None and np.ndim(rest) == 1 and len(rest) != group.shape[0]:
            raise InputError(
                f"{table.path}.rest_length",
                f"has {len(rest)} values for {group.shape[0]} springs",
                "give one per spring",
            )
        table.finish()
        pairs.append(group)
        rests.append(rest)
        if named:
            groups.append((name, group.shape[0]))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64), None, []
    springs = np.concatenate(pairs)
    if all(rest is None for rest in rests):
        return springs, None, groups
    if any(rest is None for rest in rests):
        raise InputError(
            "springs.rest_length", "given for some groups only", "give it for every [[springs]] table or none"
        )
    rest_length = np.concatenate([np.broadcast_to(np.asarray(r, float), (p.shape[0],)) for r, p in zip(rests, pairs)])
    return springs, rest_length, groups


def _array(value):
    if isinstance(value, dict):  # per spring group
        return {group: _array(v) for group, v in value.items()}
    return jnp.asarray(np.asarray(value, dtype=float), dtype=float)
