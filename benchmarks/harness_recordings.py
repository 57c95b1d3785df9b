"""Harness recordings: a wire harness (a parent cable with two thinner branches) swung by grippers,
simulated by a volumetric rod model that jaxspring does not contain.

Each branch is a chain of triangular cross-sections (three particles at radius r around the
centreline, sections h = 2 cm apart) joined by springs along the edges of the prism between two
sections (three along, six diagonals) and around each section. Bending and twist stiffness come
from the geometry (EI about EA r^2 / 2), not from a bending term. A branch's first section is
joined to the parent's three sections around the junction by springs between all their particles,
so the branch leaves the parent rigidly, at its rest angle and twist. Written here in plain JAX,
independent of jaxspring's simulator; jaxspring only writes the files. Run:
python benchmarks/harness_recordings.py --out DIR [--train 8 --held-out 14 --frames 500 --grasp ends]

Rod (SI units, y up, gravity (0, -9.81, 0)). Parent: 0.8 m, r = 6 mm, EA = 400 N, 0.25 kg/m,
natural curvature 0.4 1/m in the horizontal plane. Branch A leaves parent section 15 (0.30 m) at
70 degrees, 0.30 m, r = 4 mm, EA = 250 N, 0.12 kg/m, natural curvature 1.0 1/m. Branch B leaves
section 28 (0.56 m) at -80 degrees, 0.24 m, r = 3.5 mm, EA = 200 N, 0.10 kg/m, straight. Springs
along: k = EA / (3 h); diagonals k / 2; around a section and at a junction k. Dashpots on every
spring's stretch rate (0.02 x k x 1 ms), quadratic air drag 3e-3 N s^2/m^2 per section,
symplectic Euler at dt = 5e-5 s in float64 (importing this module turns on jax_enable_x64).

Grippers. "ends": gripper A holds the parent's sections 0-2, gripper B its sections 38-40.
"middle": gripper B holds sections 19-21 instead (the parent's far half hangs free). The harness
first settles for 2 s with extra damping while gripper B moves 0.15 m towards A (it sags); then
each gripper moves by a sum of three sinusoids per axis (amplitude 0.02-0.08 m, 0.2-0.8 Hz, at
most 2 m/s^2) and turns by two per axis (0.05-0.3 rad) about its centre, ramped in over 0.5 s.

Observation: 18 markers at section centroids, the parent's first (sections 0, 2, 6, 11, 15, 20,
24, 28, 33, 38, 40), then branch A's (4, 8, 12, 15 sections from the junction), then branch
B's (4, 8, 12), at 100 Hz; 1 mm Gaussian noise on every coordinate and frame; 1-2 drop-outs of
3-8 frames on free markers. `truth.json` holds every setting, the marker tree (`edges`) and the
driven markers (`driven`: 0, 1, 9, 10 for "ends"; 0, 1, 5 for "middle").
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

H, GRAVITY, DT, FPS, NOISE = 0.02, (0.0, -9.81, 0.0), 5e-5, 100, 1e-3
BRANCHES = [  # sections after the first, radius, EA, kg/m, natural curvature, (parent section, angle [deg])
    dict(sections=40, radius=6e-3, ea=400.0, density=0.25, curvature=0.4, joint=None),
    dict(sections=15, radius=4e-3, ea=250.0, density=0.12, curvature=1.0, joint=(15, 70.0)),
    dict(sections=12, radius=3.5e-3, ea=200.0, density=0.10, curvature=0.0, joint=(28, -80.0)),
]
MARKER_SECTIONS = [[0, 2, 6, 11, 15, 20, 24, 28, 33, 38, 40], [4, 8, 12, 15], [4, 8, 12]]
GRIPS = {"ends": ([0, 1, 2], [38, 39, 40]), "middle": ([0, 1, 2], [19, 20, 21])}
DRIVEN = {"ends": [0, 1, 9, 10], "middle": [0, 1, 5]}
DAMPING_TIME, DRAG, SETTLE, SETTLE_DAMPING, RAMP, APPROACH = 1e-3 * 0.02, 3e-3, 2.0, 8.0, 0.5, 0.15
FREQUENCIES, AMPLITUDE, ACCELERATION, ANGLES = (0.2, 0.8), (0.02, 0.08), 2.0, (0.05, 0.3)


def build():
    """The rest particles (N, 3), masses (N,), springs (S, 2), rest lengths, stiffness, each
    branch's section particle indices [(sections + 1, 3)], and the marker tree."""
    points, masses, sections = [], [], []
    for spec in BRANCHES:
        if spec["joint"] is None:
            origin, heading = np.zeros(3), 0.0
            first = 0
        else:
            at, angle = spec["joint"]
            origin = centres(points, sections[0], at)
            parent = centres(points, sections[0], at + 1) - centres(points, sections[0], at - 1)
            heading = np.arctan2(-parent[2], parent[0]) + np.radians(angle)
            first = 1  # the junction section is the parent's
        ring = []
        for i in range(first, spec["sections"] + 1):
            s = i * H  # the centreline turns at the natural curvature, in the horizontal plane
            angle = heading + spec["curvature"] * s
            t = np.array([np.cos(angle), 0.0, -np.sin(angle)])
            if spec["curvature"]:
                centre = origin + np.array(
                    [
                        (np.sin(angle) - np.sin(heading)) / spec["curvature"],
                        0.0,
                        (np.cos(angle) - np.cos(heading)) / spec["curvature"],
                    ]
                )
            else:
                centre = origin + s * np.array([np.cos(heading), 0.0, -np.sin(heading)])
            normal, side = np.array([0.0, 1.0, 0.0]), np.cross(t, [0.0, 1.0, 0.0])
            ids = []
            for k in range(3):
                phi = 2 * np.pi * k / 3
                points.append(centre + spec["radius"] * (np.cos(phi) * normal + np.sin(phi) * side))
                masses.append(spec["density"] * H / 3)
                ids.append(len(points) - 1)
            ring.append(ids)
        sections.append(np.array(ring))
    x = np.array(points)
    springs, stiffness = [], []
    for b, spec in enumerate(BRANCHES):
        k_along, ring = spec["ea"] / (3 * H), sections[b]
        for i in range(len(ring)):
            for a in range(3):
                springs.append((ring[i][a], ring[i][(a + 1) % 3]))
                stiffness.append(k_along)
                if i + 1 < len(ring):
                    springs.append((ring[i][a], ring[i + 1][a]))
                    stiffness.append(k_along)
                    for d in (1, 2):
                        springs.append((ring[i][a], ring[i + 1][(a + d) % 3]))
                        stiffness.append(k_along / 2)
        if spec["joint"] is not None:
            at = spec["joint"][0]
            for j in (at - 1, at, at + 1):
                for p in sections[0][j]:
                    for q in ring[0]:
                        springs.append((p, q))
                        stiffness.append(k_along)
    springs = np.array(springs)
    rest = np.linalg.norm(x[springs[:, 1]] - x[springs[:, 0]], axis=-1)
    return x, np.array(masses), springs, rest, np.array(stiffness), sections


def centres(points, ring, i):
    return np.mean(np.asarray(points)[ring[i]], axis=0)


def marker_layout(sections):
    """Each marker's section particles (M, 3), the marker tree's edges."""
    rings, edges, first = [], [], {}
    for b, chosen in enumerate(MARKER_SECTIONS):
        ring = sections[b]
        for k, i in enumerate(chosen):
            rings.append(ring[i - (1 if BRANCHES[b]["joint"] else 0)])
            if k:
                edges.append((len(rings) - 2, len(rings) - 1))
        first[b] = len(rings) - len(chosen)
    for b, spec in enumerate(BRANCHES):
        if spec["joint"] is not None:
            edges.append((MARKER_SECTIONS[0].index(spec["joint"][0]), first[b]))
    return np.array(rings), edges


def forces(x, v, model, settle):
    springs, rest, k, masses = model["springs"], model["rest"], model["k"], model["masses"]
    d = x[springs[:, 1]] - x[springs[:, 0]]
    length = jnp.sqrt(jnp.sum(d * d, axis=-1))
    u = d / length[:, None]
    rate = jnp.sum((v[springs[:, 1]] - v[springs[:, 0]]) * u, axis=-1)
    f = (k * (length - rest) + k * DAMPING_TIME * rate)[:, None] * u
    total = jnp.zeros_like(x).at[springs[:, 0]].add(f).at[springs[:, 1]].add(-f)
    speed = jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True) + 1e-30)
    total = total - DRAG / 3 * speed * v - settle * SETTLE_DAMPING * masses[:, None] * v
    return total / masses[:, None] + jnp.asarray(GRAVITY)


def gripper_pose(t, path, g):
    """Gripper g's translation (3,) and rotation (3, 3) at time t (ramped in after the settle)."""
    ramp = 1.0 - jnp.exp(-(((t - SETTLE) / RAMP) ** 2)) * (t > SETTLE) - (t <= SETTLE)
    move = jnp.sum(path["amplitude"][g] * jnp.sin(2 * jnp.pi * path["frequency"][g] * t + path["phase"][g]), axis=-1)
    angles = jnp.sum(
        path["rot_amplitude"][g] * jnp.sin(2 * jnp.pi * path["rot_frequency"][g] * t + path["rot_phase"][g]), axis=-1
    )
    approach = jnp.where(g == 1, APPROACH * jnp.clip(t / 1.0, 0.0, 1.0), 0.0)
    translation = ramp * move + jnp.array([-1.0, 0.0, 0.0]) * approach
    a = ramp * angles
    cx, sx, cy, sy, cz, sz = jnp.cos(a[0]), jnp.sin(a[0]), jnp.cos(a[1]), jnp.sin(a[1]), jnp.cos(a[2]), jnp.sin(a[2])
    rx = jnp.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = jnp.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = jnp.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return translation, rz @ ry @ rx


def simulate(model, path, frames, dt=DT):
    """Positions (frames, N, 3) at 100 Hz after the settle."""
    x0, held = jnp.asarray(model["x"]), model["held"]
    substeps = round(1 / (FPS * dt))

    def placed(t):
        out = []
        for g in range(2):
            ids = held[g]
            centre = jnp.mean(x0[ids], axis=0)
            translation, rotation = gripper_pose(t, path, g)
            out.append(centre + translation + (x0[ids] - centre) @ rotation.T)
        return jnp.concatenate(out)

    ids = jnp.concatenate([held[0], held[1]])

    def step(state, t):
        x, v = state
        a = forces(x, v, model, (t < SETTLE).astype(x.dtype))
        v = v + dt * a
        target = placed(t + dt)
        v = v.at[ids].set((target - x[ids]) / dt)  # the held particles move with their gripper
        x = x + dt * v
        return (x, v), None

    def frame(state, t0):
        state, _ = jax.lax.scan(step, state, t0 + dt * jnp.arange(substeps))
        return state, state[0]

    state = (x0, jnp.zeros_like(x0))
    settle_frames = round(SETTLE * FPS)
    state, _ = jax.lax.scan(frame, state, jnp.arange(settle_frames) / FPS)
    _, xs = jax.lax.scan(frame, state, SETTLE + jnp.arange(frames) / FPS)
    return xs


def random_path(rng):
    frequency = rng.uniform(*FREQUENCIES, (2, 3, 3))
    amplitude = np.minimum(rng.uniform(*AMPLITUDE, (2, 3, 3)), ACCELERATION / (2 * np.pi * frequency) ** 2 / 3)
    return dict(
        amplitude=amplitude,
        frequency=frequency,
        phase=rng.uniform(0, 2 * np.pi, (2, 3, 3)),
        rot_amplitude=rng.uniform(*ANGLES, (2, 3, 2)),
        rot_frequency=rng.uniform(*FREQUENCIES, (2, 3, 2)),
        rot_phase=rng.uniform(0, 2 * np.pi, (2, 3, 2)),
    )


def make_harness_recordings(out_dir, train=8, held_out=14, seed=0, frames=500, grasp="ends", dt=DT):
    """Simulate train + held_out recordings; write them and truth.json under out_dir; the truth dict."""
    out = Path(out_dir)
    x, masses, springs, rest, k, sections = build()
    rings, edges = marker_layout(sections)
    held = [jnp.asarray(np.concatenate([sections[0][i] for i in grip])) for grip in GRIPS[grasp]]
    model = dict(
        x=x, masses=jnp.asarray(masses), springs=jnp.asarray(springs), rest=jnp.asarray(rest), k=jnp.asarray(k)
    )
    model["held"] = held
    rngs = [np.random.default_rng([seed, k]) for k in range(train + held_out)]
    paths = [random_path(rng) for rng in rngs]
    batch = {name: jnp.asarray(np.stack([p[name] for p in paths])) for name in paths[0]}
    xs = np.asarray(jax.jit(jax.vmap(lambda p: simulate(model, p, frames, dt)))(batch))
    if not np.isfinite(xs).all():
        raise RuntimeError("the harness blew up: lower dt")
    markers = xs[:, :, rings].mean(axis=3)  # section centroids, (R, F, M, 3)
    records = []
    for r, rng in enumerate(rngs):
        seen = markers[r] + rng.normal(0.0, NOISE, markers[r].shape)
        free = [m for m in range(len(rings)) if m not in DRIVEN[grasp]]
        gaps = []
        for _ in range(rng.integers(1, 3) if frames > 30 else 0):  # drop-outs inside longer takes
            m, length = int(rng.choice(free)), int(rng.integers(3, 9))
            first = int(rng.integers(8, frames - 5 - length + 1))
            seen[first : first + length, m] = np.nan
            gaps.append((m, first, length))
        file = out / ("train" if r < train else "held_out") / f"harness_{r if r < train else r - train:03d}.h5"
        file.parent.mkdir(parents=True, exist_ok=True)
        js.save_recording(
            file, js.Recording(t=np.arange(frames) / FPS, x=seen, markers=[f"m{i}" for i in range(len(rings))])
        )
        records.append(dict(file=str(file.relative_to(out)), seed=[seed, r], gaps=gaps))
    truth = dict(branches=BRANCHES, marker_sections=MARKER_SECTIONS, edges=edges, driven=DRIVEN[grasp], grasp=grasp)
    truth |= dict(gravity=GRAVITY, dt=dt, fps=FPS, frames=frames, noise_std=NOISE, section_spacing=H)
    truth |= dict(
        mass=float(masses.sum()), particles=int(x.shape[0]), springs=int(springs.shape[0]), recordings=records
    )
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    truth["files"] = [out / rec["file"] for rec in records] + [out / "truth.json"]
    return truth


def main(argv=None):
    parser = argparse.ArgumentParser(description="Write harness recordings from an independent volumetric rod.")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--train", type=int, default=8)
    parser.add_argument("--held-out", type=int, default=14)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=500, help="frames per recording at 100 Hz (default 500)")
    parser.add_argument("--grasp", choices=list(GRIPS), default="ends")
    args = parser.parse_args(argv)
    clock = time.perf_counter()
    truth = make_harness_recordings(args.out, args.train, args.held_out, args.seed, args.frames, args.grasp)
    print(
        f"{len(truth['files']) - 1} recordings, {truth['particles']} particles, {truth['mass']:.3f} kg; "
        f"edges {truth['edges']}; took {time.perf_counter() - clock:.1f} s"
    )


if __name__ == "__main__":
    main()
