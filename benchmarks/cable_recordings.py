"""Cable recordings: robot-swung cables from a discrete elastic rod, a model jaxspring does not contain.

The motion comes from a discrete elastic rod (centreline plus a twist angle per edge, after
Bergou et al. 2008), written here in plain JAX and independent of jaxspring's simulator;
jaxspring only writes the files. Run:
python benchmarks/cable_recordings.py --out DIR [--train 8 --held-out 14 --seed 0 --frames 500]

Rod (SI units, gravity (0, 0, -9.81)). A cable of length L = 1.0 m and mass 0.2 kg in E = 40
edges (41 nodes), rest edge length l = L / E. Its mass per length varies along it as
1 + 0.35 cos(pi s / L) (heavier at the first end, like a connector), lumped on the nodes. With
edge vectors e_j, tangents t_j, curvature binormals kb_i = 2 e_{i-1} x e_i / (|e_{i-1}||e_i| +
e_{i-1} . e_i) at interior nodes i, a space-parallel (Bishop) reference frame d1_j carried from
the first gripper's frame along the edges, material frames m1_j = cos(th_j) d1_j + sin(th_j) d2_j,
m2_j = t_j x m1_j, and material curvatures w_i^j = (kb_i . m2_j, -kb_i . m1_j) for j = i - 1, i:

    stretch  sum_j   EA/2 (|e_j| / l - 1)^2 l                      EA = 400 N
    bend     sum_i,j (1 / 4 l) sum_k B_k (w_ik^j - l k_k)^2       B = (0.012, 0.008) N m^2,
                                                                   natural curvature k = (1.5, 0.3) 1/m
    twist    sum_i   GJ/2 (th_i - th_{i-1})^2 / l                 GJ = 0.004 N m^2

Dissipation (Rayleigh, on the rates of the same strains): eta_s = 0.3 N s on the axial strain,
eta_b = 2e-5 N m^2 s on the curvatures, eta_t = 2e-6 N m^2 s on the twist. Air drag on every
node, across and along the cable's local tangent: f = -c_n |v_n| v_n - c_t |v_t| v_t with
c_n = 2e-3 and c_t = 5e-4 N s^2/m^2. Twist inertia 0.5 m_edge r^2, r = 5 mm. Symplectic
Euler at dt = 5e-5 s in float64 (importing this module turns on jax_enable_x64).

Grippers. Each end is clamped with its orientation: gripper A holds nodes 0..2 on a straight line
along its x axis, its z axis is the material normal m1 of edges 0 and 1 (their twist is 0);
gripper B holds nodes 38..40 likewise (its x axis pointing into the cable), and edges 38, 39 take
the twist that puts m1 on gripper B's z axis. The cable starts hanging between the grippers
0.7 m apart (settled for 2 s with extra damping). Then each gripper's position follows
p0 + r(t) sum of three A sin(2 pi f t + phi) per axis (A 0.04-0.15 m, f 0.15-0.8 Hz, at most
2.5 m/s^2), its rotation exp(r(t) sum of two a sin(...)) about each axis (a 0.1-0.5 rad), with
r(t) = 1 - exp(-(t / 0.5 s)^2); the grippers stay 0.35-0.9 m apart.

Observation: 12 markers at nodes 0, 2 (gripper A), 6, 10, ..., 34 (free cable), 38, 40 (gripper
B), at 100 Hz from t = 0; Gaussian noise of std 1 mm on every coordinate and frame; 1-3 drop-outs
of 3-8 frames on the free markers. Recorded times start at a random 1-5 s. truth.json holds every
setting. Like the real benchmark, the gripper markers are driven in a fit (`driven = [0, 1, 10,
11]` of the markers).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxspring as js

jax.config.update("jax_enable_x64", True)

LENGTH, MASS, EDGES, CLAMP = 1.0, 0.2, 40, 2
SEGMENT = LENGTH / EDGES
TRUE = dict(
    stretch=400.0,  # EA [N]
    bend=(0.012, 0.008),  # B1, B2 [N m^2]
    curvature=(1.5, 0.3),  # natural curvature in the material frame [1/m]
    twist=0.004,  # GJ [N m^2]
    eta_stretch=0.3,
    eta_bend=2e-5,
    eta_twist=2e-6,
    drag_across=2e-3,
    drag_along=5e-4,
    radius=1e-2,
)
GRAVITY = (0.0, 0.0, -9.81)
DT, FPS, NOISE = 1e-4, 100, 1e-3
SPAN, RAMP, SETTLE_TIME, SETTLE_DAMPING = 0.7, 0.5, 2.0, 10.0
FREQUENCIES, AMPLITUDE, ACCELERATION, ANGLES, SEPARATION = (0.15, 0.8), (0.04, 0.15), 2.5, (0.1, 0.5), (0.35, 0.9)
MARKER_NODES = np.array([0, 2, 6, 10, 14, 18, 22, 26, 30, 34, 38, 40])
DRIVEN_MARKERS = [0, 1, 10, 11]


def node_masses():
    """Lumped node masses [kg], (E + 1,): the line density 1 + 0.35 cos(pi s / L), scaled to MASS."""
    s = (np.arange(EDGES) + 0.5) * SEGMENT
    edge = 1 + 0.35 * np.cos(np.pi * s / LENGTH)
    edge *= MASS / edge.sum()
    return np.concatenate([[0.0], edge]) / 2 + np.concatenate([edge, [0.0]]) / 2, edge


def transport(u, ta, tb):
    """u parallel-transported from unit tangent ta to unit tangent tb (rotation about ta x tb)."""
    b, c = jnp.cross(ta, tb), jnp.dot(ta, tb)
    return c * u + jnp.cross(b, u) + jnp.dot(b, u) * b / (1 + c)


def rotation(angles):
    """Rotation matrix exp([angles]x) (Rodrigues), (3, 3)."""
    angle = jnp.sqrt(jnp.sum(angles**2) + 1e-30)
    k = angles / angle
    kx = jnp.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return jnp.eye(3) + jnp.sin(angle) * kx + (1 - jnp.cos(angle)) * kx @ kx


def grippers(t, path):
    """Gripper poses at time t: positions (2, 3) and rotations (2, 3, 3). path: dict of arrays."""
    ramp = 1 - jnp.exp(-((t / RAMP) ** 2))
    w = 2 * jnp.pi * path["frequency"]  # (2, 3, K)
    position = path["p0"] + ramp * jnp.sum(path["amplitude"] * jnp.sin(w * t + path["phase"]), axis=-1)
    wr = 2 * jnp.pi * path["rot_frequency"]
    angles = ramp * jnp.sum(path["rot_amplitude"] * jnp.sin(wr * t + path["rot_phase"]), axis=-1)  # (2, 3)
    turn = jnp.stack([rotation(angles[0]), rotation(angles[1])])
    return position, jnp.einsum("gij,gjk->gik", turn, path["R0"])


def clamped_nodes(t, path):
    """Positions (2C + 2, 3) of the clamped nodes 0..C and E - C..E, and gripper B's z axis (3,)."""
    position, rot = grippers(t, path)
    steps = jnp.arange(CLAMP + 1)[:, None] * SEGMENT
    a = position[0] + steps * rot[0][:, 0]
    b = position[1] + steps * rot[1][:, 0]  # from node E inwards
    return jnp.concatenate([a, b[::-1]]), rot[0][:, 2], rot[1][:, 2]


CLAMPED = np.concatenate([np.arange(CLAMP + 1), np.arange(EDGES - CLAMP, EDGES + 1)])
FREE_NODES = np.arange(CLAMP + 1, EDGES - CLAMP)
FREE_EDGES = np.arange(CLAMP, EDGES - CLAMP)


def signed_angle(u, w, axis):
    """Angle from u to w about `axis` (all (..., 3), u and w perpendicular to axis)."""
    return jnp.arctan2(jnp.sum(jnp.cross(u, w) * axis, -1), jnp.sum(u * w, -1))


def frames_at(x, frame):
    """Tangents and reference frames d1 (E, 3) at positions x: the stored frame's d1 moved in time
    from its tangents to x's (time-parallel transport); the clamped edges take the grippers' z axes."""
    ref_t, ref_d1, normal_a, normal_b = frame
    e = x[1:] - x[:-1]
    length = jnp.sqrt(jnp.sum(e**2, axis=-1))
    t = e / length[:, None]
    d1 = jax.vmap(transport)(ref_d1, ref_t, t)
    d1 = d1.at[:CLAMP].set(normal_a).at[EDGES - CLAMP :].set(normal_b)
    d1 = d1 - jnp.sum(d1 * t, -1, keepdims=True) * t
    return e, length, t, d1 / jnp.linalg.norm(d1, axis=-1, keepdims=True)


def strains(x, theta_free, frame, ref_twist_prev):
    """The rod's strains: axial (E,), material curvatures (E - 1, 2, 2), twist (E - 1,); and the
    reference twist (E - 1,), unwrapped next to ref_twist_prev.

    theta_free: twist angles of the free edges from their reference frames; the clamped edges
    have 0 (their m1 is the gripper's z axis).
    """
    e, length, t, d1 = frames_at(x, frame)
    moved = jax.vmap(transport)(d1[:-1], t[:-1], t[1:])  # d1_{i-1} carried across node i
    raw = signed_angle(moved, d1[1:], t[1:])
    ref_twist = ref_twist_prev + jnp.remainder(raw - ref_twist_prev + jnp.pi, 2 * jnp.pi) - jnp.pi
    d2 = jnp.cross(t, d1)
    theta = jnp.concatenate([jnp.zeros(CLAMP), theta_free, jnp.zeros(CLAMP)])
    m1 = jnp.cos(theta)[:, None] * d1 + jnp.sin(theta)[:, None] * d2
    m2 = jnp.cross(t, m1)
    kb = 2 * jnp.cross(e[:-1], e[1:]) / (length[:-1] * length[1:] + jnp.sum(e[:-1] * e[1:], axis=-1))[:, None]
    curvature = jnp.stack(
        [
            jnp.stack([jnp.sum(kb * m2[:-1], -1), -jnp.sum(kb * m1[:-1], -1)], -1),
            jnp.stack([jnp.sum(kb * m2[1:], -1), -jnp.sum(kb * m1[1:], -1)], -1),
        ],
        axis=1,
    )  # (E - 1, 2 edges, 2 axes)
    return (length / SEGMENT - 1, curvature, theta[1:] - theta[:-1] + ref_twist), ref_twist


def accelerations(x, v, theta, omega, frame, ref_twist, values, masses, extra_damping):
    """Accelerations of the free nodes (F, 3) and twist accelerations of the free edges."""

    def strain_of(x_all, th):
        return strains(x_all, th, frame, ref_twist)[0]

    s, sdot = jax.jvp(strain_of, (x, theta), (v, omega))  # the clamped nodes' motion included
    seg = SEGMENT
    bend = jnp.asarray(values["bend"])
    rest = jnp.asarray(values["curvature"]) * seg
    cot = (
        values["stretch"] * s[0] * seg + values["eta_stretch"] * sdot[0] * seg,
        (bend * (s[1] - rest) + values["eta_bend"] * sdot[1]) / (2 * seg),
        (values["twist"] * s[2] + values["eta_twist"] * sdot[2]) / seg,
    )
    _, pullback = jax.vjp(strain_of, x, theta)
    force_all, torque = pullback(cot)
    e = x[1:] - x[:-1]
    tangent = e[:-1] + e[1:]
    tf = tangent / jnp.linalg.norm(tangent, axis=-1, keepdims=True)
    tf = tf[FREE_NODES - 1]
    vf = v[FREE_NODES]
    along = jnp.sum(vf * tf, -1, keepdims=True) * tf
    across = vf - along

    def quad(u):
        return jnp.sqrt(jnp.sum(u**2, -1, keepdims=True) + 1e-30) * u

    drag = -values["drag_across"] * quad(across) - values["drag_along"] * quad(along)
    mass = masses[0][FREE_NODES][:, None]
    acc = (-force_all[FREE_NODES] + drag) / mass + jnp.asarray(GRAVITY) - extra_damping * vf
    inertia = 0.5 * masses[1][FREE_EDGES] * values["radius"] ** 2
    return acc, -torque / inertia - extra_damping * omega


def step(state, t, path, values, masses, extra_damping, dt):
    """One symplectic Euler step of the free nodes and twists; clamped nodes set from the grippers.

    state: positions, velocities (E + 1, 3), free twists and their rates, the stored tangents and
    reference frames (E, 3) each, the reference twist (E - 1,).
    """
    x, v, theta, omega, ref_t, ref_d1, ref_twist = state
    nodes, na, nb = clamped_nodes(t, path)
    rates = jax.jvp(lambda s: clamped_nodes(s, path)[0], (t,), (jnp.ones_like(t),))[1]
    x, v = x.at[CLAMPED].set(nodes), v.at[CLAMPED].set(rates)
    frame = (ref_t, ref_d1, na, nb)
    acc, alpha = accelerations(x, v, theta, omega, frame, ref_twist, values, masses, extra_damping)
    v = v.at[FREE_NODES].add(dt * acc)
    omega = omega + dt * alpha
    x = x.at[FREE_NODES].add(dt * v[FREE_NODES])
    theta = theta + dt * omega
    nodes, na, nb = clamped_nodes(t + dt, path)
    x = x.at[CLAMPED].set(nodes)
    frame = (ref_t, ref_d1, na, nb)
    _, ref_twist = strains(x, theta, frame, ref_twist)
    _, _, ref_t, ref_d1 = frames_at(x, frame)
    return (x, v, theta, omega, ref_t, ref_d1, ref_twist)


def rollout(start, path, values, frames, substeps, extra_damping=0.0, dt=DT):
    """Node positions (frames, E + 1, 3) every `substeps` steps from state `start` at t = 0."""
    masses = tuple(jnp.asarray(m) for m in node_masses())

    def frame(state, k):
        def one(state, j):
            return step(state, (k * substeps + j) * dt, path, values, masses, extra_damping, dt), None

        state, _ = jax.lax.scan(one, state, jnp.arange(substeps))
        return state, state[0]

    _, x = jax.lax.scan(frame, start, jnp.arange(frames - 1))
    return jnp.concatenate([start[0][None], x])


def hanging_shape():
    """Nodes on a parabola-like sag of the cable's length between the grippers, and the end tangents."""
    s = np.linspace(0.0, 1.0, EDGES + 1)
    for depth in np.linspace(0.0, 0.6, 6001):
        curve = np.stack([SPAN * (s - 0.5), np.zeros_like(s), -depth * 4 * s * (1 - s)], axis=1)
        if np.linalg.norm(np.diff(curve, axis=0), axis=1).sum() >= LENGTH:
            break
    fine = np.linspace(0, 1, 20001)
    dense = np.stack([SPAN * (fine - 0.5), np.zeros_like(fine), -depth * 4 * fine * (1 - fine)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    at = np.linspace(0, arc[-1], EDGES + 1)
    nodes = np.stack([np.interp(at, arc, dense[:, k]) for k in range(3)], axis=1)
    return nodes


def gripper_frames(nodes):
    """Initial gripper rotations (2, 3, 3): x along the cable inwards from each end, z up-ish."""
    frames = []
    for inward in (nodes[CLAMP] - nodes[0], nodes[EDGES - CLAMP] - nodes[EDGES]):
        ex = inward / np.linalg.norm(inward)
        ez = np.array([0.0, 0.0, 1.0]) - ex[2] * ex
        ez /= np.linalg.norm(ez)
        frames.append(np.stack([ex, np.cross(ez, ex), ez], axis=1))
    return np.stack(frames)


def still_path(nodes):
    """A path that holds both grippers at their initial poses."""
    zeros = np.zeros((2, 3, 1))
    return dict(
        p0=np.stack([nodes[0], nodes[EDGES]]),
        R0=gripper_frames(nodes),
        amplitude=zeros,
        frequency=zeros + 1.0,
        phase=zeros,
        rot_amplitude=zeros,
        rot_frequency=zeros + 1.0,
        rot_phase=zeros,
    )


def settled_start(values, dt=DT):
    """The rod hanging at rest between the still grippers after SETTLE_TIME s, as a rollout state."""
    nodes = hanging_shape()
    path = still_path(nodes)
    start = initial_state(nodes, path)
    steps = round(SETTLE_TIME / dt)
    masses = tuple(jnp.asarray(m) for m in node_masses())

    @jax.jit
    def settle(start):
        def one(state, j):
            return step(state, j * dt * 0.0, path, values, masses, SETTLE_DAMPING, dt), None

        return jax.lax.scan(one, start, jnp.arange(steps))[0]

    state = settle(start)
    return tuple(jnp.zeros_like(s) if i in (1, 3) else s for i, s in enumerate(state)), path


def initial_state(nodes, path):
    """A rollout state at `nodes` at rest: untwisted, reference frames carried along from gripper A (Bishop)."""
    e = np.diff(nodes, axis=0)
    t = e / np.linalg.norm(e, axis=1, keepdims=True)
    d1 = [path["R0"][0][:, 2]]
    for j in range(1, EDGES):
        d1.append(np.asarray(transport(jnp.asarray(d1[-1]), jnp.asarray(t[j - 1]), jnp.asarray(t[j]))))
    d1 = np.stack(d1)
    frame = (jnp.asarray(t), jnp.asarray(d1), jnp.asarray(path["R0"][0][:, 2]), jnp.asarray(path["R0"][1][:, 2]))
    x = jnp.asarray(nodes)
    _, ref_twist = strains(x, jnp.zeros(FREE_EDGES.size), frame, jnp.zeros(EDGES - 1))
    free = jnp.zeros(FREE_EDGES.size)
    return (x, jnp.zeros_like(x), free, free, jnp.asarray(t), jnp.asarray(d1), ref_twist)


def random_path(rng, base, duration):
    """A gripper path: base's initial poses, sinusoids within the amplitude, acceleration and separation limits."""
    frequency = rng.uniform(*FREQUENCIES, (2, 3, 3))
    shared = rng.uniform(*AMPLITUDE, (1, 3, 3)).repeat(2, axis=0)
    amplitude = np.minimum(shared * rng.uniform(0.6, 1.0, (2, 3, 3)), ACCELERATION / (2 * np.pi * frequency) ** 2)
    phase = rng.uniform(0, 2 * np.pi, (2, 3, 3))
    path = dict(
        base,
        amplitude=amplitude,
        frequency=frequency,
        phase=phase,
        rot_amplitude=rng.uniform(*ANGLES, (2, 3, 2)),
        rot_frequency=rng.uniform(*FREQUENCIES, (2, 3, 2)),
        rot_phase=rng.uniform(0, 2 * np.pi, (2, 3, 2)),
    )
    t = np.arange(0.0, duration, 0.01)
    for _ in range(60):  # shrink until the grippers stay within the separation range
        ends = np.asarray(jax.vmap(lambda s: grippers(s, path)[0])(t))
        distance = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1)
        if SEPARATION[0] <= distance.min() and distance.max() <= SEPARATION[1]:
            break
        path["amplitude"] = path["amplitude"] * np.array([1.0, 0.85])[:, None, None]
    return path


def observe(x, rng):
    """Noisy marker positions (F, M, 3) with 1-3 drop-outs on free markers; the gaps as (marker, first, length)."""
    seen = x[:, MARKER_NODES] + rng.normal(0.0, NOISE, (x.shape[0], MARKER_NODES.size, 3))
    gaps = []
    for _ in range(rng.integers(1, 4)):
        marker, length = int(rng.integers(2, MARKER_NODES.size - 2)), int(rng.integers(3, 9))
        first = int(rng.integers(8, x.shape[0] - 5 - length + 1))
        seen[first : first + length, marker] = np.nan
        gaps.append((marker, first, length))
    return seen, gaps


def make_cable_recordings(out_dir, train=8, held_out=14, seed=0, frames=500, values=None, dt=DT):
    """Simulate train + held_out recordings; write them and truth.json under out_dir.

    Recording k (train first, then held out) draws its gripper paths, noise, drop-outs and time
    offset from numpy seed [seed, k]. `values` overrides entries of TRUE.

    Returns:
        dict (also in truth.json): every setting, per recording its file, seed, gaps and the
        largest marker speed; and "files".

    Example:
        >>> truth = make_cable_recordings("/tmp/cable", train=2, held_out=1, frames=100)
    """
    out, values = Path(out_dir), {**TRUE, **(values or {})}
    traced = {k: jnp.asarray(v) for k, v in values.items()}
    start, base = settled_start(traced, dt)
    rngs = [np.random.default_rng([seed, k]) for k in range(train + held_out)]
    paths = [random_path(rng, base, frames / FPS) for rng in rngs]
    batch = {k: np.stack([p[k] for p in paths]) for k in paths[0]}
    substeps = round(1 / (FPS * dt))
    simulate = jax.jit(
        jax.vmap(lambda p: rollout(start, p, traced, frames, substeps, 0.0, dt)),
    )
    x = np.asarray(simulate(batch))
    speed = np.linalg.norm(np.diff(x[:, :, MARKER_NODES], axis=1), axis=-1).max(axis=(1, 2)) * FPS
    strain = np.linalg.norm(np.diff(x, axis=2), axis=-1) / SEGMENT - 1
    if not np.isfinite(x).all():
        raise RuntimeError("the rod blew up: lower dt")
    records = []
    for k, rng in enumerate(rngs):
        file = out / ("train" if k < train else "held_out") / f"cable_{k if k < train else k - train:03d}.h5"
        file.parent.mkdir(parents=True, exist_ok=True)
        markers, gaps = observe(x[k], rng)
        t = rng.uniform(1.0, 5.0) + np.arange(frames) / FPS
        js.save_recording(file, js.Recording(t=t, x=markers, markers=[f"m{i}" for i in range(MARKER_NODES.size)]))
        records.append(
            dict(file=str(file.relative_to(out)), seed=[seed, k], t0=float(t[0]), gaps=gaps, max_speed=float(speed[k]))
        )
    truth = dict(values={k: np.asarray(v).tolist() for k, v in values.items()}, gravity=GRAVITY, edges=EDGES)
    truth |= dict(length=LENGTH, mass=MASS, clamp_edges=CLAMP, integrator="symplectic_euler", dt=dt, fps=FPS)
    truth |= dict(frames=frames, noise_std=NOISE, marker_nodes=MARKER_NODES.tolist(), driven_markers=DRIVEN_MARKERS)
    truth |= dict(seed=seed, max_marker_speed=float(speed.max()), strain=[float(strain.min()), float(strain.max())])
    truth |= dict(recordings=records)
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    truth["files"] = [out / r["file"] for r in records] + [out / "truth.json"]
    return truth


def main(argv=None):
    """Command line: write the recordings and truth.json, and say what was written."""
    parser = argparse.ArgumentParser(description="Write cable recordings from an independent discrete elastic rod.")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--train", type=int, default=8, help="training recordings (default 8)")
    parser.add_argument("--held-out", type=int, default=14, help="held-out recordings (default 14)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=500, help="frames per recording at 100 Hz (default 500)")
    args = parser.parse_args(argv)
    clock = time.perf_counter()
    truth = make_cable_recordings(args.out, args.train, args.held_out, args.seed, args.frames)
    print("\n".join(str(file) for file in truth["files"]))
    print(f"max marker speed {truth['max_marker_speed']:.2f} m/s, strain {truth['strain'][0]:.4f} to ", end="")
    print(f"{truth['strain'][1]:.4f}; took {time.perf_counter() - clock:.1f} s")


if __name__ == "__main__":
    main()
