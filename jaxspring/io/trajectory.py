"""Trajectory files (HDF5, docs/file-formats.md) with atomic writes."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import glob
import os
import tempfile
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np

from ..errors import FileFormatError, InputError
from ..resources import check_hdf5_read
from ..sim.checks import check_params
from ..sim.model import make_model
from ..sim.params import Params
from ..sim.scene import Scene
from ..sim.state import State, Trajectory

TRAJECTORY_FORMAT = "jaxspring.trajectory"
FORMAT_VERSION = 1


def write_rows_csv(rows, path):
    """Write dataclass rows as CSV (header: the field names), atomically."""
    rows = list(rows)
    with atomic_path(Path(path)) as tmp, open(tmp, "w", newline="") as handle:
        writer = csv.writer(handle)
        if rows:
            writer.writerow([f.name for f in dataclasses.fields(rows[0])])
        writer.writerows(dataclasses.astuple(row) for row in rows)


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path`; rename it onto `path` only on success.

    An interrupted write never leaves a half file under the final name.

    Example:
        >>> with atomic_path("out.h5") as tmp:
        ...     write_everything(tmp)
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError("out", f"folder {str(folder)!r} does not exist", "create it or choose another path")
    _remove_stale(folder, path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=f".tmp{path.suffix}", dir=folder)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
        _fsync_folder(folder)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _remove_stale(folder: Path, path: Path) -> None:
    """Delete temporary files of earlier writes to `path` whose process no longer runs (killed
    mid-write); a write in progress by a live process is left alone."""
    for stale in folder.glob(f".{glob.escape(path.name)}.*.tmp{glob.escape(path.suffix)}"):
        pid = stale.name[len(path.name) + 2 :].split(".", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            with contextlib.suppress(OSError):
                stale.unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _fsync_folder(folder: Path) -> None:
    """Make the rename durable: fsync the folder's entry list (where the OS allows)."""
    try:
        handle = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(handle)
    except OSError:
        pass
    finally:
        os.close(handle)


def open_hdf5(path: Path, remedy: str) -> h5py.File:
    """`path` opened for reading, or a one-line `FileFormatError` ending in `remedy` when it is
    not a readable HDF5 file (truncated, or another format)."""
    try:
        return h5py.File(path, "r")
    except OSError:
        raise FileFormatError(f"{path}: not a readable HDF5 file (truncated or another format); {remedy}") from None


def save_trajectory(path, scene: Scene, trajectory: Trajectory) -> None:
    """Write a trajectory and the scene that made it to an HDF5 file, atomically.

    Example:
        >>> js.save_trajectory("cloth.h5", scene, traj)
    """
    from ..version import __version__

    x = np.asarray(trajectory.x)
    model = scene.model
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(
            format=TRAJECTORY_FORMAT,
            format_version=FORMAT_VERSION,
            scene=scene.name,
            integrator=model.integrator.name,
            dt=model.dt,
            dtype=str(x.dtype),
            jaxspring_version=__version__,
        )
        group = f.create_group("params")
        for name, value in scene.params.to_dict().items():
            group.create_dataset(name, data=np.asarray(value))
        topo = f.create_group("topology")
        topo.create_dataset("springs", data=np.asarray(model.springs, dtype=np.int32))
        topo.create_dataset("rest_length", data=np.asarray(model.rest_length))
        topo.create_dataset("mass", data=np.asarray(model.mass))
        topo.create_dataset("pinned", data=np.asarray(model.pinned, dtype=bool))
        topo.create_dataset("drag", data=np.asarray(model.drag, dtype=bool))
        if scene.faces is not None and len(scene.faces):
            topo.create_dataset("faces", data=np.asarray(scene.faces, dtype=np.int32))
        if scene.lattice_shape is not None:
            topo.attrs["lattice_shape"] = np.asarray(scene.lattice_shape, dtype=np.int64)
        if model.spring_groups:  # names and spring counts, in spring order
            topo.attrs["spring_group_names"] = [name for name, _ in model.spring_groups]
            topo.attrs["spring_group_counts"] = np.asarray([n for _, n in model.spring_groups], dtype=np.int64)
        traj = f.create_group("trajectory")
        traj.create_dataset("t", data=np.asarray(trajectory.t))
        traj.create_dataset("x", data=x)
        traj.create_dataset("v", data=np.asarray(trajectory.v))


def _check_trajectory_arrays(path, t, x, v, springs, rest_length, mass, faces, lattice, params) -> None:
    """One-line errors for a trajectory file whose arrays are inconsistent or not finite."""

    def bad(what: str):
        return FileFormatError(f"{path}: {what}; re-create the file with `jaxspring run`")

    for name, value in params.items():
        if not np.issubdtype(np.asarray(value).dtype, np.number):
            raise bad(f"parameter {name!r} is not numeric")
    if x.ndim != 3 or x.shape[0] == 0:
        raise bad(f"the trajectory has no frames (x of shape {x.shape})")
    if not (np.issubdtype(t.dtype, np.number) and np.all(np.isfinite(t))):
        raise bad("frame times t are not finite numbers")
    if t.ndim == 1 and t.shape[0] > 1 and np.any(np.diff(t) <= 0):
        raise bad("frame times t are not strictly increasing")
    if mass.ndim != 1:
        raise bad(f"topology/mass has shape {mass.shape}, expected (N,)")
    if springs.ndim != 2 or springs.shape[1:] != (2,) or rest_length.shape != (springs.shape[0],):
        raise bad(f"springs {springs.shape} and rest_length {rest_length.shape} disagree")
    count = mass.shape[0]
    if faces.size and (faces.ndim != 2 or faces.min() < 0 or faces.max() >= count):
        raise bad(f"a face index lies outside 0..{count - 1}")
    if lattice is not None and (min(lattice, default=0) < 1 or int(np.prod(lattice)) != count):
        raise bad(f"lattice_shape {lattice} does not hold the {count} particles")


def load_trajectory(path, max_memory: int | None = None) -> tuple[Scene, Trajectory]:
    """Read a trajectory file; returns (scene, trajectory).

    The scene is rebuilt from the file (topology, params, integrator, dt) with
    frame 0 as its state; a params entry absent from the file means that force
    is not in the scene. A file whose arrays exceed the memory available (or
    `max_memory` bytes) is refused before it is read.

    Example:
        >>> scene, traj = js.load_trajectory("cloth.h5")
    """
    path = Path(path)
    if not path.exists():
        raise FileFormatError(f"{path}: file not found; check the path")
    if not path.is_file():  # a device or a FIFO would be read forever
        raise FileFormatError(f"{path}: not a regular file; give a trajectory file written by `jaxspring run`")
    with open_hdf5(path, "re-create it with `jaxspring run`") as f:
        if f.attrs.get("format") != TRAJECTORY_FORMAT:
            raise FileFormatError(
                f"{path}: not a jaxspring trajectory (format={f.attrs.get('format')!r}); give a file written by `jaxspring run`"
            )
        try:
            version = int(f.attrs.get("format_version", -1))
        except (TypeError, ValueError):
            version = str(f.attrs.get("format_version"))
        if version != FORMAT_VERSION:
            raise FileFormatError(
                f"{path}: format_version {version} is not supported; this jaxspring reads version {FORMAT_VERSION}"
            )
        check_hdf5_read(f, path, max_memory)
        try:
            params = {name: np.asarray(f["params"][name][()]) for name in f["params"]}
            topo = f["topology"]
            springs = np.asarray(topo["springs"][()])
            rest_length = np.asarray(topo["rest_length"][()])
            mass = np.asarray(topo["mass"][()])
            pinned = np.asarray(topo["pinned"][()], dtype=bool)
            drag = np.asarray(topo["drag"][()], dtype=bool)
            faces = np.asarray(topo["faces"][()]) if "faces" in topo else np.zeros((0, 3), dtype=np.int32)
            lattice = tuple(int(n) for n in topo.attrs["lattice_shape"]) if "lattice_shape" in topo.attrs else None
            groups = list(
                zip(
                    [str(n) for n in topo.attrs.get("spring_group_names", [])],
                    [int(n) for n in topo.attrs.get("spring_group_counts", [])],
                )
            )
            t = np.asarray(f["trajectory/t"][()])
            x = np.asarray(f["trajectory/x"][()])
            v = np.asarray(f["trajectory/v"][()])
            integrator, dt = str(f.attrs["integrator"]), float(f.attrs["dt"])
            name = str(f.attrs.get("scene", path.stem))
        except (KeyError, OSError, TypeError, ValueError, AttributeError) as exc:
            raise FileFormatError(
                f"{path}: incomplete or malformed trajectory file ({exc}); re-create it with `jaxspring run`"
            ) from None
    _check_trajectory_arrays(path, t, x, v, springs, rest_length, mass, faces, lattice, params)
    unknown = sorted({name.partition(".")[0] for name in params} - set(Params.names()))
    if unknown:
        raise FileFormatError(f"{path}: unknown parameter {unknown[0]!r}; this file was written by a newer jaxspring")
    if x.ndim != 3 or x.shape[2] != 3 or x.shape != v.shape or t.shape != (x.shape[0],) or x.shape[1] != mass.shape[0]:
        raise FileFormatError(
            f"{path}: trajectory shapes disagree (x {x.shape}, v {v.shape}, t {t.shape}); re-create the file"
        )
    try:
        model = make_model(
            springs,
            mass,
            rest_length=rest_length,
            pinned=pinned,
            drag=drag,
            gravity="gravity" in params,
            ground="kg" in params,
            integrator=integrator,
            dt=dt,
            lattice_shape=lattice,
            spring_groups=groups,
        )
        values = {k: jnp.asarray(v, dtype=float) for k, v in params.items()}
        scene_params = check_params(model, Params.from_values(values))
    except InputError as exc:
        raise exc.within(str(path)) from None
    trajectory = Trajectory(x=jnp.asarray(x), v=jnp.asarray(v), t=jnp.asarray(t))
    stride = trajectory.stride(dt)
    scene = Scene(
        name=name,
        model=model,
        params=scene_params,
        state=State(x=jnp.asarray(x[0], dtype=float), v=jnp.asarray(v[0], dtype=float)),
        faces=faces,
        steps=int(x.shape[0] - 1) * stride,
        save_every=stride,
        lattice_shape=lattice,
    )
    return scene, trajectory
