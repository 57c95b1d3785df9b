"""A cable scene built from its recordings: particles through the markers, rest shape from the data.

A tracked cable has a few markers; `cable_scene` threads a chain of particles through them
(`subdivide` particle intervals between two neighbouring free markers), with stretch springs
(i, i + 1) and either bend springs (i, i + 2) or, with `bending=True`, the bending term on
every three neighbours (a rod's stiffness kb and damping kbd on the turning angle, which
leaves stretching to the stretch springs), so that the cable bends smoothly between markers
instead of at them. The rest shape comes from the data, not a straight line: each marker
interval's rest chord is the median over every seen frame of the markers' distance, and the
shape within and across intervals (the natural curvature) is that of a reference frame,
interpolated by a centripetal Catmull-Rom spline through its markers. Each end is clamped with its
orientation by driving two of its markers (`driven`, marker indices), which hold the end's
tangent; `groups` splits the springs of the free cable into that many consecutive
segment groups (`stretch_1`, `bend_1`, ...), each with its own stiffness and damping.

The result is a scene file's table (`scene`), the particle carrying each marker (`markers`)
and the driven particles (`driven`), ready for `js.scene_from_dict` and
`js.recording_target`, or as TOML text for a scene file (`toml()`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import InputError
from ..sim.checks import whole_number

MAX_PARTICLES = 100_000
"""Most particles a cable scene is built with (`subdivide` beyond that is refused, not built)."""
STANDARD_GRAVITY = 9.81
"""m/s^2: the size of an inferred gravity vector."""
AXIS_DEGREES = 10.0
"""An inferred down direction this close to a coordinate axis is taken as that axis."""
DISAGREE_DEGREES = 45.0
"""A given gravity this far from the direction the markers sag is refused (a wrong up axis)."""
LEAST_SAG = 1e-3
"""Mean sag, as a fraction of the cable's marker-to-marker length, below which no down is read."""


def sag_direction(recordings, length: float):
    """The unit direction the cable's inner markers hang from the line between its end markers,
    averaged over every frame of `recordings` (a hanging cable sags along gravity), or None when
    the mean sag is below `LEAST_SAG` of `length` (a taut or a floating cable shows no down)."""
    total, seen = np.zeros(3), 0
    for r in recordings:
        x = np.asarray(r.x, dtype=float)
        chord = x[:, -1] - x[:, 0]
        size = np.linalg.norm(chord, axis=-1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            u = chord / size
        rel = x[:, 1:-1] - x[:, :1]
        across = rel - np.sum(rel * u[:, None], axis=-1, keepdims=True) * u[:, None]
        ok = np.isfinite(across).all(axis=-1) & (size > 0)
        total += np.where(ok[..., None], across, 0.0).sum(axis=(0, 1))
        seen += int(ok.sum())
    if not seen or not np.linalg.norm(total) / seen >= LEAST_SAG * length:
        return None
    return total / np.linalg.norm(total)


def cable_gravity(recordings, gravity, length: float) -> tuple[list, str]:
    """(gravity [m/s^2], a sentence on where it came from): `gravity` as given, checked against
    the markers' sag, or with None inferred from it (`sag_direction`), snapped to a coordinate
    axis within `AXIS_DEGREES`."""
    down = sag_direction(recordings, length)
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
        return vector.tolist(), f"gravity {vector.tolist()} m/s^2, as given"
    if down is None:
        raise InputError(
            "gravity",
            "cannot be inferred: the inner markers do not sag away from the line between the end markers",
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


@dataclasses.dataclass(frozen=True)
class CableModel:
    """A cable scene table with its marker and driven particles (see the module docstring).

    Attributes:
        scene: the scene table (a dict `js.scene_from_dict` reads).
        markers: the particle carrying marker k, (M,).
        driven: the driven particles (of the driven markers).
    """

    scene: dict
    markers: list
    driven: list
    gravity_note: str = ""

    def toml(self) -> str:
        """The scene as the text of a scene file."""
        s, p = self.scene, self.scene["physics"]
        lines = [f"name = {_q(s['name'])}", f"description = {_q(s['description'])}", f"dt = {s['dt']!r}"]
        lines += [f"integrator = {_q(s['integrator'])}", "", "[physics]"]
        for key in ("ks", "kd"):
            lines.append(f"{key} = {{ " + ", ".join(f"{g} = {v!r}" for g, v in p[key].items()) + " }")
        lines += [f"cd = {p['cd']!r}"] + [f"{key} = {p[key]!r}" for key in ("kb", "kbd") if key in p]
        lines += [f"gravity = {list(p['gravity'])!r}", "", "[particles]"]
        part = s["particles"]
        lines.append("x = [" + ", ".join("[" + ", ".join(f"{c!r}" for c in x) + "]" for x in part["x"]) + "]")
        lines += ["mass = [" + ", ".join(f"{m!r}" for m in part["mass"]) + "]", "drag = true"]
        for group in s["springs"]:
            lines += ["", "[[springs]]", f"name = {_q(group['name'])}"]
            lines.append("pairs = [" + ", ".join(f"[{i}, {j}]" for i, j in group["pairs"]) + "]")
            lines.append("rest_length = [" + ", ".join(f"{r!r}" for r in group["rest_length"]) + "]")
        if "bending" in s:
            triples = ", ".join(f"[{a}, {b}, {c}]" for a, b, c in s["bending"]["triples"])
            lines += ["", "[bending]", f"triples = [{triples}]"]
        return "\n".join(lines) + "\n"


def cable_scene(
    recordings,
    driven=(0, 1, -2, -1),
    subdivide: int = 1,
    groups: int = 1,
    mass: float = 1.0,
    rest: str = "data",
    bending: bool = False,
    reference: tuple = (0, 0),
    values=None,
    dt: float = 1e-3,
    name: str = "cable",
    gravity=None,
) -> CableModel:
    """A cable through the markers of `recordings` (marker k next to marker k + 1 along it).

    Args:
        recordings: `js.Recording`s of one cable (the same markers in each).
        driven: marker indices moved as recorded; two at each end clamp it with its orientation.
        subdivide: particle intervals between two neighbouring markers that are not both driven.
        groups: consecutive segment groups of the free cable's springs, each fitted on its own.
        mass: the cable's mass [kg], spread over the particles by their share of the arc length.
        rest: "data" (arc lengths and curvature from the recordings) or "straight" (a straight
            cable as long as the median marker distances).
        bending: bend the cable with the bending term (a `[bending]` table: every three
            neighbouring particles, one stiffness kb and damping kbd, rest curvature from the
            rest shape) instead of bend springs (i, i + 2).
        reference: (recording, frame) whose marker shape gives the rest curvature.
        values: {"ks": ..., "kd": ..., "cd": ..., "kb": ..., "kbd": ...} starting values (per
            length: ks and kd are given for a 1 m spring and scaled by 1 / rest length; kb [N m^2]
            and kbd [N m^2 s] are a rod's, independent of the particles); defaults suit a 1 m cable.
        dt: the scene's time step [s].
        gravity: [m/s^2] in the recordings' axes. None (default): inferred from the direction the
            cable's inner markers sag from the line between its ends, snapped to a coordinate axis
            within 10 degrees, printed and written into the scene (`cable_gravity`). A given vector
            more than 45 degrees from that direction is refused: a wrong up axis would fit the
            wrong physics without a word.

    Example:
        >>> cable = js.cable_scene(recordings, subdivide=2, mass=0.2)
        >>> scene = js.scene_from_dict(cable.scene)
        >>> target = js.recording_target(scene, recordings, markers=cable.markers, driven=cable.driven)
    """
    recordings = list(recordings)
    if not recordings:
        raise InputError("recordings", "none given", "give the cable's recordings")
    count = recordings[0].marker_count
    if any(r.marker_count != count for r in recordings):
        raise InputError("recordings", "have different marker counts", "give recordings of one marker set")
    if count < 3:
        raise InputError("recordings", f"have {count} markers", "a cable needs at least 3 markers")
    subdivide, groups = whole_number("subdivide", subdivide), whole_number("groups", groups)
    if subdivide < 1 or groups < 1:
        raise InputError("subdivide/groups", "must be at least 1", "give positive integers")
    if (count - 1) * subdivide + 1 > MAX_PARTICLES:
        raise InputError(
            "subdivide",
            f"{subdivide} particle intervals per marker interval make {(count - 1) * subdivide + 1} particles",
            f"subdivide less (at most {MAX_PARTICLES} particles)",
        )
    if groups > (count - 1) * subdivide:
        raise InputError(
            "groups", f"{groups} groups for at most {(count - 1) * subdivide} springs", "give fewer segment groups"
        )
    if rest not in ("data", "straight"):
        raise InputError("rest", f"is {rest!r}", 'give "data" or "straight"')
    driven_markers = _driven_markers(driven, count)
    chords = np.concatenate([np.linalg.norm(np.diff(r.x, axis=1), axis=-1) for r in recordings])
    if not np.isfinite(chords).any(axis=0).all():
        raise InputError("recordings", "two neighbouring markers are never seen together", "check the marker order")
    median = np.nanmedian(chords, axis=0)  # (M - 1,)
    if not (median > 0).all():
        k = int(np.argmin(median > 0))
        raise InputError(
            "recordings",
            f"markers {k} and {k + 1} are at one place in most frames (median distance 0)",
            "give each marker its own place on the cable (check the tracking)",
        )
    splits = [1 if (k in driven_markers and k + 1 in driven_markers) else int(subdivide) for k in range(count - 1)]
    markers = np.concatenate([[0], np.cumsum(splits)]).astype(int)
    if rest == "straight":
        x = np.zeros((markers[-1] + 1, 3))
        x[:, 0] = np.concatenate([[0.0], np.cumsum(np.repeat(median / splits, splits))])
        stretch = np.ones(x.shape[0] - 1)
    else:
        try:
            rec_index, frame = reference
        except (TypeError, ValueError):
            raise InputError("reference", f"is {reference!r}", "give (recording, frame), e.g. (0, 0)") from None
        rec_index, frame = whole_number("reference", rec_index), whole_number("reference", frame)
        if not 0 <= rec_index < len(recordings):
            raise InputError(
                "reference",
                f"recording {rec_index} is outside 0..{len(recordings) - 1}",
                "give the index of one of the recordings",
            )
        shape = _reference_shape(recordings[rec_index], frame)
        if not (np.linalg.norm(np.diff(shape, axis=0), axis=-1) > 0).all():
            raise InputError(
                "reference",
                f"two neighbouring markers are at one place in frame {frame}",
                'choose another reference frame, or rest = "straight"',
            )
        x = _spline(shape, splits)
        # each interval's rest chord is the median seen distance, not this one frame's
        stretch = np.repeat(median / np.linalg.norm(np.diff(shape, axis=0), axis=-1), splits)
    n = x.shape[0]
    segment = np.linalg.norm(np.diff(x, axis=0), axis=-1) * stretch
    share = np.zeros(n)
    share[:-1] += segment / 2
    share[1:] += segment / 2
    particle_mass = mass * share / share.sum()
    values = {"ks": 400.0, "kd": 0.3, "cd": 2e-3, "kb": 0.01, "kbd": 1e-4, **(values or {})}
    low = [markers[d] for d in driven_markers if d < count / 2]
    high = [markers[d] for d in driven_markers if d >= count / 2]
    first, last = (max(low) if low else 0), (min(high) if high else n - 1)
    springs, ks, kd = [], {}, {}
    for family, gap in (("stretch", 1),) if bending else (("stretch", 1), ("bend", 2)):
        pairs = np.stack([np.arange(n - gap), np.arange(gap, n)], axis=1)
        group = _group_of((pairs[:, 0] + pairs[:, 1]) / 2, first, last, int(groups))
        for g in range(int(groups)):
            label = family if groups == 1 else f"{family}_{g + 1}"
            chosen = pairs[group == g]
            if not chosen.size:
                continue
            factor = np.array([stretch[i:j].mean() for i, j in chosen])
            rest_length = np.linalg.norm(x[chosen[:, 1]] - x[chosen[:, 0]], axis=-1) * factor
            scale = 1.0 if family == "stretch" else 0.05  # bend springs start 20x softer
            ks[label] = float(f"{scale * values['ks'] / rest_length.mean():.6g}")
            kd[label] = float(f"{scale * values['kd'] / rest_length.mean():.6g}")
            springs.append({"name": label, "pairs": chosen.tolist(), "rest_length": rest_length.tolist()})
    vector, note = cable_gravity(recordings, gravity, float(median.sum()))
    if gravity is None:
        print(note)
    physics = {"ks": ks, "kd": kd, "cd": float(values["cd"]), "gravity": vector}
    if bending:
        physics.update(kb=float(values["kb"]), kbd=float(values["kbd"]))
    scene = {
        "name": name,
        "description": (
            f"A cable of {n} particles through {count} markers ({subdivide} per marker interval), "
            f"{'rest shape from the recordings' if rest == 'data' else 'straight at rest'}, {groups} segment group(s), "
            f"{'the bending term' if bending else 'bend springs'}; {note}."
        ),
        "dt": float(dt),
        "integrator": "semi_implicit_euler",
        "physics": physics,
        "particles": {"x": x.tolist(), "mass": particle_mass.tolist(), "drag": True},
        "springs": springs,
    }
    if bending:  # rest curvature: the scene's default, that of its rest shape x
        scene["bending"] = {"triples": [[i - 1, i, i + 1] for i in range(1, n - 1)]}
    driven_particles = [int(markers[k]) for k in driven_markers]
    return CableModel(scene=scene, markers=markers.tolist(), driven=driven_particles, gravity_note=note)


def _driven_markers(driven, count: int) -> list[int]:
    """The driven marker indices (negative ones from the end), sorted; each problem an InputError."""
    if isinstance(driven, (str, bytes)) or np.ndim(driven) != 1:
        raise InputError("driven", f"is {driven!r}", "give a list of marker indices, e.g. [0, 1, -2, -1]")
    out = []
    for d in driven:
        k = whole_number("driven", d)
        if not -count <= k < count:
            raise InputError(
                "driven", f"marker {k} is outside -{count}..{count - 1}", f"give indices of the {count} markers"
            )
        if k % count in out:
            raise InputError("driven", f"names marker {k % count} twice", "give each driven marker once")
        out.append(k % count)
    return sorted(out)


def _group_of(middle, first, last, groups):
    """Segment group of each spring by its middle's place between particles first and last."""
    if groups == 1:
        return np.zeros(middle.shape, dtype=int)
    where = np.clip((middle - first) / max(last - first, 1), 0.0, 1.0 - 1e-12)
    return np.floor(where * groups).astype(int)


def _reference_shape(recording, frame):
    """The markers at `frame`, lost ones filled from the nearest frame where they were seen, (M, 3)."""
    x = np.array(recording.x)
    if not 0 <= frame < x.shape[0]:  # a negative frame is refused, not counted from the end
        raise InputError("reference", f"frame {frame} is outside 0..{x.shape[0] - 1}", "give a frame of the recording")
    shape = x[frame].copy()
    for k in np.flatnonzero(~np.isfinite(shape).all(axis=-1)):
        seen = np.flatnonzero(np.isfinite(x[:, k]).all(axis=-1))
        shape[k] = x[seen[np.argmin(np.abs(seen - frame))], k]
    return shape


def _spline(shape, splits):
    """Particles on the centripetal Catmull-Rom spline through `shape`'s markers (M, 3), with
    splits[k] equal parameter steps between markers k and k + 1, (1 + sum(splits), 3)."""
    # one more point at each end, extrapolated by the quadratic through the end's three markers
    before, after = 3 * shape[0] - 3 * shape[1] + shape[2], 3 * shape[-1] - 3 * shape[-2] + shape[-3]
    # where that point falls on the end marker (markers in a line, spaced 1 : 2), a straight continuation
    if not np.linalg.norm(before - shape[0]) > 1e-9 * np.linalg.norm(shape[1] - shape[0]):
        before = 2 * shape[0] - shape[1]
    if not np.linalg.norm(after - shape[-1]) > 1e-9 * np.linalg.norm(shape[-1] - shape[-2]):
        after = 2 * shape[-1] - shape[-2]
    padded = np.concatenate([[before], shape, [after]])
    points = [shape[0]]
    for k, s in enumerate(splits):
        points += [_catmull_rom(*padded[k : k + 4], u) for u in np.arange(1, s + 1) / s]
    return np.array(points)


def _catmull_rom(p0, p1, p2, p3, u):
    """The centripetal Catmull-Rom point between p1 (u = 0) and p2 (u = 1)."""
    t0 = 0.0
    t1 = t0 + np.linalg.norm(p1 - p0) ** 0.5
    t2 = t1 + np.linalg.norm(p2 - p1) ** 0.5
    t3 = t2 + np.linalg.norm(p3 - p2) ** 0.5
    t = t1 + u * (t2 - t1)
    a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
    a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
    a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
    b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
    b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
    return (t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2


def _q(text: str) -> str:
    """`text` as a TOML basic string: backslashes, quotes and control characters (a line
    break in a name) escaped, so the scene file parses back to the same text."""
    out = []
    for ch in str(text):
        if ch in ('"', "\\"):
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'
