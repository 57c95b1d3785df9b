"""Which way is down for an object recorded in its own axes: read from how it sags, or checked.

Motion capture is often z up, vision data y up: gravity is never assumed. A hanging object sags
along gravity, so its markers say where down is: between two held places the inner markers sag
from the line joining them. Held at one place only, an object shows no such sag: gravity must
then be given.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .cable_tree import tree_path

STANDARD_GRAVITY = 9.81
"""m/s^2: the size of an inferred gravity vector."""
AXIS_DEGREES = 15.0
"""An inferred down direction this close to a coordinate axis is taken as that axis. The sag read
includes the rest shape's own bow (natural curvature across the chord): on the branched benchmark
the reading is 6-11 degrees off the true down."""
DISAGREE_DEGREES = 45.0
"""A given gravity this far from the direction the markers sag is refused (a wrong up axis)."""
LEAST_SAG = 1e-3
"""Mean sag, as a fraction of the cable's marker-to-marker length, below which no down is read."""
HELD_APART = 2 / 3
"""Driven markers at least this fraction of the object's longest path (leaf to leaf) apart hold
it at two places and it sags between them; closer ones (one gripper, or an end and the middle,
where a stiff arm beyond the middle hold can lever the span between up) show no reliable down."""


def sag_direction(recordings, length: float, path=None):
    """The unit direction the inner markers of `path` (marker indices from one held end to the
    other; default: every marker in order) sag from the line between its end markers, averaged
    over every frame of `recordings` (an object held at two places sags along gravity between
    them), or None when the mean sag is below `LEAST_SAG` of `length` (a taut or a floating
    cable shows no down)."""
    total, seen = np.zeros(3), 0
    for r in recordings:
        x = np.asarray(r.x, dtype=float)
        path = list(range(x.shape[1])) if path is None else list(path)
        chord = x[:, path[-1]] - x[:, path[0]]
        size = np.linalg.norm(chord, axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            u = chord / size
        rel = x[:, path[1:-1]] - x[:, path[:1]]
        across = rel - np.sum(rel * u[:, None], axis=-1, keepdims=True) * u[:, None]
        ok = np.isfinite(across).all(axis=-1) & (size > 0)
        total += np.where(ok[..., None], across, 0.0).sum(axis=(0, 1))
        seen += int(ok.sum())
    if not seen or not np.linalg.norm(total) / seen >= LEAST_SAG * length:
        return None
    return total / np.linalg.norm(total)


def cable_gravity(recordings, gravity, length: float, path=None, grasp=False) -> tuple[list, str]:
    """(gravity [m/s^2], a sentence on where it came from): `gravity` as given, checked against
    the sag of the markers of `path` (`sag_direction`), or with None inferred from it, snapped to
    a coordinate axis within `AXIS_DEGREES`. With `grasp` (the object is held at one place only)
    there is no sag to read: a given vector is taken unchecked, and None is refused."""
    down = None if grasp else sag_direction(recordings, length, path=path)
    if gravity is not None:
        try:
            vector = np.asarray(gravity, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise InputError("gravity", f"is {gravity!r}", "give three numbers in m/s^2, e.g. (0, -9.81, 0)") from None
        if not np.isfinite(vector).all():
            raise InputError("gravity", f"is {vector.tolist()}", "give three finite numbers in m/s^2")
        size = np.linalg.norm(vector)
        if down is not None and size > 0:
            angle = float(np.degrees(np.arccos(np.clip(vector @ down / size, -1.0, 1.0))))
            if angle > DISAGREE_DEGREES:
                raise InputError(
                    "gravity",
                    f"{vector.tolist()} is {angle:.0f} degrees from the direction the markers sag "
                    f"({np.round(down, 2).tolist()})",
                    "check the recordings' up axis, or leave gravity out to infer it",
                )
        unchecked = " (unchecked: a single grasp shows no sag)" if grasp else ""
        return vector.tolist(), f"gravity {vector.tolist()} m/s^2, as given{unchecked}"
    if down is None:
        raise InputError(
            "gravity",
            "cannot be inferred: "
            + (
                "the object is held at one place only, so no sag between two holds shows where down is"
                if grasp
                else "the inner markers do not sag away from the line between the end markers"
            ),
            "give gravity in the recordings' axes, e.g. gravity=(0, -9.81, 0) for y up, (0, 0, -9.81) for z up",
        )
    axis = int(np.argmax(np.abs(down)))
    off = float(np.degrees(np.arccos(min(abs(float(down[axis])), 1.0))))
    if off <= AXIS_DEGREES:
        down = np.where(np.arange(3) == axis, np.sign(down[axis]), 0.0)
    vector = [float(f"{STANDARD_GRAVITY * d:.6g}") + 0.0 for d in down]
    sign = "-" if down[axis] < 0 else "+"
    words = (
        f"gravity {vector} m/s^2, inferred from how the markers sag ({off:.0f} degrees from {sign}{'xyz'[axis]}); "
        "give gravity if that is not down"
    )
    return vector, words


def sag_markers(layout, driven_markers, median) -> dict:
    """Where the sag is read (`cable_gravity`'s keywords): the tree path between the two driven
    markers farthest apart, when they are at least `HELD_APART` of the longest leaf-to-leaf path
    apart (with nothing driven, that longest path); else a single grasp."""
    length = {}
    for (u, v), m in zip(layout.order, median, strict=True):
        length[(u, v)] = length[(v, u)] = m

    def farthest(ends):
        best, far = None, 0.0
        for i, a in enumerate(ends):
            for b in ends[i + 1 :]:
                path = tree_path(layout.adjacent, a, b)
                arc = sum(length[pair] for pair in zip(path[:-1], path[1:], strict=True))
                if arc > far:
                    best, far = path, arc
        return best, far

    longest, span = farthest([k for k, a in enumerate(layout.adjacent) if len(a) == 1])
    if not driven_markers:
        return {"path": longest}
    held, apart = farthest(driven_markers)
    return {"path": held} if held is not None and apart >= HELD_APART * span else {"grasp": True}
