"""The marker graph of a rod-like object: a tree of marker edges, checked, and laid out as particles.

A cable is a chain of markers; a wire harness is a tree (a parent cable with branches). The
edges (i, j) join markers that are neighbours along the object. `marker_edges` checks them
(every problem one `InputError` naming the edge and the fix); `TreeLayout` numbers the
particles (markers and the particles between them) in depth-first order from the first leaf,
so a chain 0-1-...-(M-1) is numbered as before: marker k at particle k * subdivide. Where a
branch goes on through a junction is read from the rest shape: the neighbour that turns least.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..sim.checks import whole_number


def marker_edges(edges, count: int) -> list[tuple[int, int]]:
    """The edges as (i, j) pairs of marker indices in 0..count-1 (negative ones from the end),
    checked to form a tree over every marker. None: the chain 0-1-...-(count-1)."""
    if edges is None:
        return [(k, k + 1) for k in range(count - 1)]
    if isinstance(edges, (str, bytes)):
        raise InputError("edges", f"is {edges!r}", "give marker index pairs, e.g. [(0, 1), (1, 2)]")
    try:
        pairs = [tuple(e) for e in edges]
    except TypeError:
        raise InputError("edges", f"is {edges!r}", "give marker index pairs, e.g. [(0, 1), (1, 2)]") from None
    root = list(range(count))

    def find(a):
        while root[a] != a:
            root[a] = root[root[a]]
            a = root[a]
        return a

    out, seen = [], set()
    for pair in pairs:
        if len(pair) != 2:
            raise InputError("edges", f"{pair!r} is not a pair of marker indices", "write each edge as (i, j)")
        i, j = (whole_number("edges", k) for k in pair)
        for k in (i, j):
            if not -count <= k < count:
                raise InputError(
                    "edges",
                    f"edge ({i}, {j}): marker {k} is outside -{count}..{count - 1}",
                    f"give indices of the {count} markers",
                )
        i, j = i % count, j % count
        if i == j:
            raise InputError("edges", f"edge ({i}, {j}) joins marker {i} to itself", "remove that edge")
        if (min(i, j), max(i, j)) in seen:
            raise InputError("edges", f"edge ({i}, {j}) is given twice", "give each edge once")
        if find(i) == find(j):
            raise InputError(
                "edges",
                f"edge ({i}, {j}) closes a cycle",
                "remove one edge of the cycle: the markers of a cable or harness form a tree",
            )
        root[find(i)] = find(j)
        seen.add((min(i, j), max(i, j)))
        out.append((i, j))
    used = {k for pair in out for k in pair}
    for k in range(count):
        if k not in used:
            raise InputError(
                "edges",
                f"marker {k} is in no edge",
                f"join it to its neighbour along the object, e.g. ({k}, {k - 1 if k else 1})",
            )
    if len(out) != count - 1:
        apart = [k for k in range(count) if find(k) != find(0)]
        raise InputError(
            "edges", f"markers {apart} are not joined to marker 0", "add the edge that joins the two parts"
        )
    return out


def neighbours(edges, count: int) -> list[list[int]]:
    """Each marker's neighbours, in increasing index."""
    out = [[] for _ in range(count)]
    for i, j in edges:
        out[i].append(j)
        out[j].append(i)
    return [sorted(n) for n in out]


def tree_path(adjacent, a: int, b: int) -> list[int]:
    """The markers on the tree's path from a to b, both included."""
    before = {a: None}
    todo = [a]
    while todo:
        u = todo.pop()
        for w in adjacent[u]:
            if w not in before:
                before[w] = u
                todo.append(w)
    path = [b]
    while path[-1] != a:
        path.append(before[path[-1]])
    return path[::-1]


def straightest(shape, adjacent, u: int, v: int):
    """The neighbour of v (not u) that turns least from the direction u -> v at rest (None at a leaf)."""
    others = [w for w in adjacent[v] if w != u]
    if not others:
        return None
    d = shape[v] - shape[u]
    d = d / np.linalg.norm(d)
    turn = [-float(d @ (shape[w] - shape[v]) / np.linalg.norm(shape[w] - shape[v])) for w in others]
    return others[int(np.argmin(turn))]


def continuation(shape, adjacent, u: int, v: int):
    """Where the branch through u and v goes on beyond v: v's neighbour w that turns least from
    u -> v, where u is also the neighbour that turns least from w -> v (None at a leaf, and where
    u -> v is a side branch meeting a junction v)."""
    w = straightest(shape, adjacent, u, v)
    return w if w is not None and straightest(shape, adjacent, w, v) == u else None


class TreeLayout:
    """Particles of a marker tree: the depth-first edge order, each marker's particle, and the
    particle pairs along each edge (`splits[e]` particle intervals on edge e).

    Attributes:
        order: the edges as directed (u, v) pairs, in depth-first order from the root.
        markers: the particle of marker k, (M,).
        count: the number of particles.
    """

    def __init__(self, edges, count: int):
        self.adjacent = neighbours(edges, count)
        self.root = next(k for k in range(count) if len(self.adjacent[k]) == 1)
        self.order, stack, seen = [], [self.root], {self.root}
        while stack:  # depth-first, lowest neighbour first (a chain: 0 -> 1 -> 2 ...)
            u = stack[-1]
            nxt = next((w for w in self.adjacent[u] if w not in seen), None)
            if nxt is None:
                stack.pop()
                continue
            seen.add(nxt)
            self.order.append((u, nxt))
            stack.append(nxt)
        self.marker_count = count
        self.is_chain = all(len(n) <= 2 for n in self.adjacent)

    def number(self, splits) -> None:
        """Number the particles with `splits[e]` intervals on the e-th edge of `order`."""
        self.splits = [int(s) for s in splits]
        self.markers = np.zeros(self.marker_count, dtype=int)
        self.markers[self.root] = 0
        self.edge_particles, n = [], 1
        for (u, v), s in zip(self.order, self.splits, strict=True):
            inside = list(range(n, n + s - 1))
            self.markers[v] = n + s - 1
            self.edge_particles.append([int(self.markers[u])] + inside + [int(self.markers[v])])
            n += s
        self.count = n

    def springs(self):
        """The stretch springs (a, b), along each edge in order, and the edge of each, (S, 2), (S,)."""
        pairs, edge = [], []
        for e, chain in enumerate(self.edge_particles):
            pairs += list(zip(chain[:-1], chain[1:], strict=True))
            edge += [e] * (len(chain) - 1)
        return np.array(pairs, dtype=int), np.array(edge, dtype=int)

    def triples(self, x, most_turn_degrees: float = 180.0):
        """Bend triples (a, b, c), b in increasing order and a < c: every pair of b's neighbours,
        except, at a junction, pairs that turn more than `most_turn_degrees` at rest in x."""
        pairs, _ = self.springs()
        around = [[] for _ in range(self.count)]
        for a, b in pairs:
            around[a].append(b)
            around[b].append(a)
        out = []
        for b in range(self.count):
            near = sorted(around[b])
            for i, a in enumerate(near):
                for c in near[i + 1 :]:
                    if len(near) > 2:
                        u, w = x[b] - x[a], x[c] - x[b]
                        cos = u @ w / (np.linalg.norm(u) * np.linalg.norm(w))
                        if np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) > most_turn_degrees:
                            continue
                    out.append((a, b, c))
        return np.array(out, dtype=int).reshape(-1, 3)

    def branches(self, shape) -> list[int]:
        """The branch of each edge of `order`: an edge goes on the branch of the edge before it
        where it is that edge's `continuation` at rest (`shape`: markers, (M, 3)), and starts a
        new branch otherwise (numbered in order)."""
        into, out, count = {}, [], 0
        for e, (u, v) in enumerate(self.order):
            before = into.get(u)
            if before is not None and continuation(shape, self.adjacent, self.order[before][0], u) == v:
                out.append(out[before])
            else:
                out.append(count)
                count += 1
            into[v] = e
        return out


def reference_frame(recordings, reference):
    """The markers at the reference (recording, frame), lost ones filled from the nearest frame
    where they were seen, (M, 3)."""
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
    x = np.array(recordings[rec_index].x)
    if not 0 <= frame < x.shape[0]:  # a negative frame is refused, not counted from the end
        raise InputError("reference", f"frame {frame} is outside 0..{x.shape[0] - 1}", "give a frame of the recording")
    shape = x[frame].copy()
    for k in np.flatnonzero(~np.isfinite(shape).all(axis=-1)):
        seen = np.flatnonzero(np.isfinite(x[:, k]).all(axis=-1))
        shape[k] = x[seen[np.argmin(np.abs(seen - frame))], k]
    return shape


def tree_spline(shape, layout):
    """Particles on centripetal Catmull-Rom splines through the markers `shape` (M, 3): on each
    edge (u, v), the spline through the markers where its branch goes on beyond u and v
    (`continuation`; where it ends, at a leaf or a junction, a point extrapolated by the
    quadratic through the end and the next two markers), with the edge's split in equal
    parameter steps, (layout.count, 3)."""
    x = np.zeros((layout.count, 3))
    x[layout.markers[layout.root]] = shape[layout.root]
    adjacent = layout.adjacent
    for (u, v), chain in zip(layout.order, layout.edge_particles, strict=True):
        before_marker, after_marker = continuation(shape, adjacent, v, u), continuation(shape, adjacent, u, v)
        before, after = (
            _beyond(shape, u, v, before_marker, after_marker),
            _beyond(shape, v, u, after_marker, before_marker),
        )
        s = len(chain) - 1
        x[chain[1:]] = [_catmull_rom(before, shape[u], shape[v], after, t) for t in np.arange(1, s + 1) / s]
    return x


def _beyond(shape, u, v, neighbour, far):
    """The spline's control point beyond marker u (away from v): u's `neighbour` there; at a leaf,
    3u - 3v + far (the quadratic through u, v and v's neighbour `far`), or 2u - v (a straight
    continuation) where there is no `far` or that point falls on u."""
    if neighbour is not None:
        return shape[neighbour]
    point = 3 * shape[u] - 3 * shape[v] + shape[far] if far is not None else shape[u]
    if not np.linalg.norm(point - shape[u]) > 1e-9 * np.linalg.norm(shape[v] - shape[u]):
        point = 2 * shape[u] - shape[v]
    return point


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
