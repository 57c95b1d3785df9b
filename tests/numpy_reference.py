"""An independent, loop-based NumPy/Python implementation of DESIGN.md section 2.

Written from the formulas, not from jaxspring's code: one Python loop over
springs and one over particles per step, plain float arithmetic, float64.
"""

import math

import numpy as np


def reference_rollout(x0, v0, springs, rest, mass, pinned, drag, params, dt, steps, save_every, driven=None):
    """Semi-implicit Euler; returns positions (frames, N, 3) and velocities (frames, N, 3).

    `driven` maps a particle to its path, a function of time giving (3,): at each step
    from t to t + dt the particle is put at path(t) with velocity (path(t + dt) - path(t)) / dt
    for the force, and at path(t + dt) after it.
    """
    driven = driven or {}
    x = [list(map(float, p)) for p in np.asarray(x0)]
    v = [list(map(float, p)) for p in np.asarray(v0)]
    n = len(x)
    springs = [(int(a), int(b)) for a, b in np.asarray(springs)]
    rest = [float(r) for r in np.asarray(rest)]
    mass = [float(m) for m in np.asarray(mass)]
    pinned = [bool(p) for p in np.asarray(pinned)]
    drag = [bool(d) for d in np.asarray(drag)]

    def per(name, count):
        value = params.get(name)
        if value is None:
            return None
        value = np.asarray(value, dtype=float)
        return [float(value)] * count if value.ndim == 0 else [float(c) for c in value]

    ks, kd = per("ks", len(springs)), per("kd", len(springs))
    cd, kg, kgd = per("cd", n), per("kg", n), per("kgd", n)
    gravity = None if params.get("gravity") is None else [float(g) for g in params["gravity"]]
    height = None if params.get("ground_height") is None else float(params["ground_height"])

    xs, vs = [np.array(x)], [np.array(v)]
    for step in range(1, steps + 1):
        ends = {}
        for i, path in driven.items():
            here, there = np.asarray(path((step - 1) * dt), float), np.asarray(path(step * dt), float)
            x[i], v[i], ends[i] = list(here), list((there - here) / dt), list(there)
        force = [[0.0, 0.0, 0.0] for _ in range(n)]
        for s, (a, b) in enumerate(springs):
            d = [x[b][k] - x[a][k] for k in range(3)]
            length = math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
            if length == 0.0:
                continue
            u = [c / length for c in d]
            closing = sum((v[b][k] - v[a][k]) * u[k] for k in range(3))
            magnitude = ks[s] * (length - rest[s]) + kd[s] * closing
            for k in range(3):
                force[a][k] += magnitude * u[k]
                force[b][k] -= magnitude * u[k]
        for i in range(n):
            if gravity is not None:
                for k in range(3):
                    force[i][k] += mass[i] * gravity[k]
            if cd is not None and drag[i]:
                speed = math.sqrt(v[i][0] ** 2 + v[i][1] ** 2 + v[i][2] ** 2)
                for k in range(3):
                    force[i][k] -= cd[i] * speed * v[i][k]
            if height is not None and x[i][1] < height:
                force[i][1] += kg[i] * (height - x[i][1]) - kgd[i] * v[i][1]
        for i in range(n):
            if pinned[i]:
                v[i] = [0.0, 0.0, 0.0]
                continue
            if i in ends:
                x[i] = ends[i]
                continue
            for k in range(3):
                v[i][k] += dt * force[i][k] / mass[i]
                x[i][k] += dt * v[i][k]
        if step % save_every == 0:
            xs.append(np.array(x))
            vs.append(np.array(v))
    return np.stack(xs), np.stack(vs)


def reference_for_scene(scene, steps, save_every=1, params=None):
    """Run the reference on a jaxspring Scene's arrays (only data is taken from it)."""
    model = scene.model
    values = {k: np.asarray(v) for k, v in (params or scene.params).to_dict().items()}
    return reference_rollout(
        scene.state.x,
        scene.state.v,
        model.springs,
        model.rest_length,
        model.mass,
        model.pinned,
        model.drag,
        values,
        model.dt,
        steps,
        save_every,
    )
