"""A cable or harness scene built from its recordings: particles through the markers, rest shape from the data.

A tracked cable has a few markers; `cable_scene` threads particles through them along the
marker tree's edges (a chain by default, any tree for a harness with branches; `subdivide`
particle intervals between two neighbouring markers that are not both driven), with stretch
springs between neighbouring particles and either bend springs or, with `bending=True`, the
bending term on every particle's two neighbours (at a junction on every two of its
neighbours): a rod's stiffness kb and damping kbd on the turning angle, which leaves
stretching to the stretch springs, so that the cable bends smoothly between markers instead
of at them. The rest shape comes from the data, not a straight line: each marker interval's
rest chord is the median over every seen frame of the markers' distance, and the shape
within and across intervals (the natural curvature) is that of a reference frame,
interpolated by centripetal Catmull-Rom splines through its markers (`cable_tree`). Each end
is clamped with its orientation by driving two of its markers (`driven`, marker indices,
anywhere on the object); `groups` splits a chain's free springs into that many consecutive
segment groups (`stretch_1`, `bend_1`, ...), or gives each branch its own ("branch").
Gravity is given or read from the sag (`sag`), never assumed.

The result is a scene file's table (`scene`), the particle carrying each marker (`markers`)
and the driven particles (`driven`), ready for `js.scene_from_dict` and
`js.recording_target`, or as the text of a scene file (`toml()`) and of an experiment that
fits it (`experiment()`): what `jaxspring cable` writes.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import InputError
from ..sim.checks import whole_number
from .cable_tree import TreeLayout, marker_edges, reference_frame, tree_spline
from .sag import cable_gravity, sag_markers

MAX_PARTICLES = 100_000
"""Most particles a cable scene is built with (`subdivide` beyond that is refused, not built)."""
JUNCTION_MOST_TURN = 150.0
"""Degrees: two neighbours of a junction that turn more than this at rest (a branch nearly folded
back on another) get no bending triple: 2 tan(theta / 2) is too steep there to step."""


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
    edges: list = dataclasses.field(default_factory=list)

    @property
    def params(self) -> list[str]:
        """The names of every value the scene has to fit: each spring group's stiffness and
        damping, the drag, and the bending stiffness and damping where it bends by the term."""
        p = self.scene["physics"]
        names = [f"{key}.{group}" for group in p["ks"] for key in ("ks", "kd")] + ["cd"]
        return names + [key for key in ("kb", "kbd") if key in p]

    def experiment(self, recordings, start: int = 5, smooth: int = 5, evaluate=(), scene: str = "cable.toml") -> str:
        """The text of an experiment file that fits this scene (every value of `params`) to
        `recordings` (paths or globs, as written in the file: relative to it), and predicts the
        `evaluate` recordings; `scene` is the scene file's path, relative to the experiment."""
        start, smooth = whole_number("start", start), whole_number("smooth", smooth)
        if start < 1 or smooth < 0:
            raise InputError("start/smooth", f"are {start}/{smooth}", "give start >= 1 and smooth >= 0")

        def paths(items):
            return "[" + ", ".join(_q(str(item)) for item in items) + "]"

        lines = [f"name = {_q(self.scene['name'])}", f"description = {_q(self.scene['description'])}"]
        lines += [f"scene = {_q(scene)}", "", "[target]", f"recordings = {paths(recordings)}"]
        if self.markers != list(range(len(self.markers))):
            lines.append(f"markers = {self.markers}   # the particle carrying each marker")
        lines += [f"driven = {self.driven}   # particles moved as their markers were recorded"]
        lines += [f"start = {start}", f"smooth = {smooth}", "", "[fit]", f"params = {paths(self.params)}"]
        if evaluate:
            lines += ["", "[evaluate]", f"recordings = {paths(evaluate)}"]
        return "\n".join(lines) + "\n"

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
    groups: int | str = 1,
    mass: float = 1.0,
    rest: str = "data",
    bending: bool = False,
    reference: tuple = (0, 0),
    values=None,
    dt: float = 1e-3,
    name: str = "cable",
    gravity=None,
    edges=None,
) -> CableModel:
    """A cable or a branched cable (a tree) through the markers of `recordings`.

    Args:
        recordings: `js.Recording`s of one object (the same markers in each).
        driven: marker indices moved as recorded, anywhere on the object; two at each end clamp
            it with its orientation, one or two in the middle are a grasp there.
        subdivide: particle intervals between two neighbouring markers that are not both driven.
        groups: consecutive segment groups of a chain's free springs, each fitted on its own;
            or "branch": one group per branch (a branch goes on through a junction where it
            turns least at rest), for a harness whose branches are thinner than their parent.
        mass: the object's mass [kg], spread over the particles by their share of the arc length.
        rest: "data" (arc lengths and curvature from the recordings) or "straight" (a straight
            chain as long as the median marker distances; chains only).
        bending: bend the object with the bending term (a `[bending]` table: every three
            neighbouring particles, and at a junction every two of its neighbours, one stiffness
            kb and damping kbd, rest curvature from the rest shape) instead of bend springs
            between the same pairs.
        reference: (recording, frame) whose marker shape gives the rest curvature.
        values: {"ks": ..., "kd": ..., "cd": ..., "kb": ..., "kbd": ...} starting values (per
            length: ks and kd are given for a 1 m spring and scaled by 1 / rest length; kb [N m^2]
            and kbd [N m^2 s] are a rod's, independent of the particles); defaults suit a 1 m cable.
        dt: the scene's time step [s].
        gravity: [m/s^2] in the recordings' axes. None (default): inferred from the direction the
            markers sag from the line between the two held places farthest apart, snapped to a
            coordinate axis within 15 degrees, printed and written into the scene
            (`cable_gravity`); refused where the object is held at one place only (no sag shows
            down there: give it). A given vector more than 45 degrees from the sag is refused: a
            wrong up axis would fit the wrong physics without a word.
        edges: marker index pairs (i, j) that are neighbours along the object, forming a tree
            over every marker (default: the chain 0-1-...-(M-1)). A marker with three or more
            neighbours is a junction.

    Example:
        >>> cable = js.cable_scene(recordings, subdivide=2, mass=0.2)
        >>> scene = js.scene_from_dict(cable.scene)
        >>> target = js.recording_target(scene, recordings, markers=cable.markers, driven=cable.driven)
    """
    try:
        recordings = list(recordings)
    except TypeError:
        raise InputError("recordings", f"is {recordings!r:.60}", "give a list of js.Recording") from None
    if not all(hasattr(r, "x") and hasattr(r, "marker_count") for r in recordings):
        raise InputError("recordings", "are not all js.Recording", "load them with js.load_recording")
    if not recordings:
        raise InputError("recordings", "none given", "give the cable's recordings")
    count = recordings[0].marker_count
    if any(r.marker_count != count for r in recordings):
        raise InputError("recordings", "have different marker counts", "give recordings of one marker set")
    if count < 3:
        raise InputError("recordings", f"have {count} markers", "a cable needs at least 3 markers")
    try:
        mass = float(mass)
    except (TypeError, ValueError):
        raise InputError("mass", f"is {mass!r:.40}", "give the object's mass in kg, e.g. 0.2") from None
    if not (math.isfinite(mass) and mass > 0):
        raise InputError("mass", f"is {mass}", "give a positive mass in kg, e.g. 0.2")
    layout = TreeLayout(marker_edges(edges, count), count)
    subdivide = whole_number("subdivide", subdivide)
    if groups != "branch":
        groups = whole_number("groups", groups)
    if subdivide < 1 or (groups != "branch" and groups < 1):
        raise InputError("subdivide/groups", "must be at least 1", 'give positive integers (or groups = "branch")')
    if (count - 1) * subdivide + 1 > MAX_PARTICLES:
        raise InputError(
            "subdivide",
            f"{subdivide} particle intervals per marker interval make {(count - 1) * subdivide + 1} particles",
            f"subdivide less (at most {MAX_PARTICLES} particles)",
        )
    if groups != "branch" and groups > 1 and not layout.is_chain:
        raise InputError("groups", f"{groups} consecutive groups need a chain of markers", 'give groups = "branch"')
    if groups != "branch" and groups > (count - 1) * subdivide:
        raise InputError(
            "groups", f"{groups} groups for at most {(count - 1) * subdivide} springs", "give fewer segment groups"
        )
    if rest not in ("data", "straight"):
        raise InputError("rest", f"is {rest!r}", 'give "data" or "straight"')
    if rest == "straight" and not layout.is_chain:
        raise InputError("rest", '"straight" needs a chain of markers', 'give rest = "data" for a branched object')
    driven_markers = _driven_markers(driven, count)
    ends = np.array(layout.order)
    chords = np.concatenate([np.linalg.norm(r.x[:, ends[:, 1]] - r.x[:, ends[:, 0]], axis=-1) for r in recordings])
    for (u, v), ever in zip(layout.order, np.isfinite(chords).any(axis=0), strict=True):
        if not ever:
            raise InputError(
                "recordings",
                f"markers {u} and {v} (edge ({u}, {v})) are never seen together",
                "check the marker order or the edges",
            )
    median = np.nanmedian(chords, axis=0)  # per edge of layout.order
    if not (median > 0).all():
        u, v = layout.order[int(np.argmin(median > 0))]
        raise InputError(
            "recordings",
            f"markers {u} and {v} are at one place in most frames (median distance 0)",
            "give each marker its own place on the cable (check the tracking)",
        )
    splits = [1 if (u in driven_markers and v in driven_markers) else subdivide for u, v in layout.order]
    layout.number(splits)
    markers, n = layout.markers, layout.count
    pairs, on_edge = layout.springs()
    if rest == "straight":  # a chain numbered from one end: particles in a line
        x = np.zeros((n, 3))
        x[:, 0] = np.concatenate([[0.0], np.cumsum(np.repeat(median / splits, splits))])
        stretch = np.ones(n - 1)
        shape = x[markers]
    else:
        shape = reference_frame(recordings, reference)
        apart = np.linalg.norm(shape[ends[:, 1]] - shape[ends[:, 0]], axis=-1)
        if not (apart > 0).all():
            u, v = layout.order[int(np.argmin(apart > 0))]
            raise InputError(
                "reference",
                f"neighbouring markers {u} and {v} are at one place in frame {reference[1]}",
                'choose another reference frame, or rest = "straight"',
            )
        x = tree_spline(shape, layout)
        # each interval's rest chord is the median seen distance, not this one frame's
        stretch = (median / apart)[on_edge]
    segment = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=-1) * stretch
    share = np.zeros(n)
    np.add.at(share, pairs[:, 0], segment / 2)
    np.add.at(share, pairs[:, 1], segment / 2)
    particle_mass = mass * share / share.sum()
    values = {"ks": 400.0, "kd": 0.3, "cd": 2e-3, "kb": 0.01, "kbd": 1e-4, **(values or {})}
    triples = layout.triples(x, JUNCTION_MOST_TURN)
    spring_of = {(int(a), int(b)): k for k, (a, b) in enumerate(pairs)}
    spring_of.update({(b, a): k for (a, b), k in list(spring_of.items())})
    if groups == "branch":
        spring_group = np.array(layout.branches(shape))[on_edge]
        group_count = int(spring_group.max()) + 1
    else:
        # a chain is numbered along itself: the ends' driven particles by their place on it
        low = [markers[d] for d in driven_markers if markers[d] < (n - 1) / 2]
        high = [markers[d] for d in driven_markers if markers[d] >= (n - 1) / 2]
        first, last = (max(low) if low else 0), (min(high) if high else n - 1)
        spring_group = _group_of((pairs[:, 0] + pairs[:, 1]) / 2, first, last, groups)
        group_count = groups
    springs, ks, kd = [], {}, {}
    for family in ("stretch",) if bending else ("stretch", "bend"):
        if family == "stretch":
            chosen_all, factor_all, group = pairs, stretch, spring_group
        else:
            chosen_all = triples[:, [0, 2]]
            first_half = np.array([spring_of[(a, b)] for a, b, _ in triples], dtype=int)
            second_half = np.array([spring_of[(b, c)] for _, b, c in triples], dtype=int)
            factor_all = (stretch[first_half] + stretch[second_half]) / 2
            group = (
                spring_group[first_half]
                if groups == "branch"
                else _group_of(chosen_all.mean(axis=1), first, last, groups)
            )
        for g in range(group_count):
            label = family if group_count == 1 else f"{family}_{g + 1}"
            chosen = chosen_all[group == g]
            if not chosen.size:
                continue
            rest_length = np.linalg.norm(x[chosen[:, 1]] - x[chosen[:, 0]], axis=-1) * factor_all[group == g]
            scale = 1.0 if family == "stretch" else 0.05  # bend springs start 20x softer
            ks[label] = float(f"{scale * values['ks'] / rest_length.mean():.6g}")
            kd[label] = float(f"{scale * values['kd'] / rest_length.mean():.6g}")
            springs.append({"name": label, "pairs": chosen.tolist(), "rest_length": rest_length.tolist()})
    vector, note = cable_gravity(
        recordings, gravity, float(median.sum()), **sag_markers(layout, driven_markers, median)
    )
    if gravity is None:
        print(note)
    physics = {"ks": ks, "kd": kd, "cd": float(values["cd"]), "gravity": vector}
    if bending:
        physics.update(kb=float(values["kb"]), kbd=float(values["kbd"]))
    junctions = sum(len(a) > 2 for a in layout.adjacent)
    what = "A cable" if layout.is_chain else f"A branched cable ({junctions} junction(s))"
    grouping = "one group per branch" if groups == "branch" else f"{groups} segment group(s)"
    scene = {
        "name": name,
        "description": (
            f"{what} of {n} particles through {count} markers ({subdivide} per marker interval), "
            f"{'rest shape from the recordings' if rest == 'data' else 'straight at rest'}, {grouping}, "
            f"{'the bending term' if bending else 'bend springs'}; {note}."
        ),
        "dt": float(dt),
        "integrator": "semi_implicit_euler",
        "physics": physics,
        "particles": {"x": x.tolist(), "mass": particle_mass.tolist(), "drag": True},
        "springs": springs,
    }
    if bending:  # rest curvature: the scene's default, that of its rest shape x
        scene["bending"] = {"triples": triples.tolist()}
    driven_particles = [int(markers[k]) for k in driven_markers]
    return CableModel(
        scene=scene,
        markers=markers.tolist(),
        driven=driven_particles,
        gravity_note=note,
        edges=[tuple(e) for e in marker_edges(edges, count)],
    )


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
