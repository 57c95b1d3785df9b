"""Rope recordings: motion-capture-like test data that the fitted model did not produce.

A finer, different rope model, written here in plain JAX and independent of jaxspring's simulator,
makes the motion; jaxspring only writes the files. Run:
python benchmarks/rope_recordings.py --out DIR [--train 8 --held-out 4 --seed 0 --frames 500]

Generator (SI units). A rope of length L = 1.0 m and mass 0.2 kg is N = 56 equal particles,
m = 0.2 / 56 kg, rest spacing l = L / 55. Two spring groups of pairs (i, i + g):

    stretch  g = 1  ks = 2000 N/m   kd = 0.5 N s/m    rest length l
    bend     g = 2  ks = 50 N/m     kd = 0.05 N s/m   rest length 2 l

ks_stretch keeps the axial stiffness EA = ks l of a 12-particle chain with 400 N/m per link:
400 (1/11) = ks (1/55), so ks = 400 * 55/11 = 2000 N/m. The bend springs carry tension too (a
uniform strain e pulls with l e (ks_stretch + 4 ks_bend)), so the rope's EA is l (2000 + 4 * 50)
= 40 N, 10 % above the chain's. Across a joint of angle theta they are 2 l cos(theta / 2) long, so
they resist folding only to fourth order in theta: 50 N/m would stop a sharp kink, but on this
smooth rope their bending part moves the markers by ~0.05 mm rms and their tension part by ~1 mm.
Forces on particle a from a spring (a, b), with d = x_b - x_a, u = d / |d|, and on every particle:

    spring   f_a = [ks (|d| - rest) + kd ((v_b - v_a) . u)] u,   f_b = -f_a
    drag     f = -cd |v| v, cd = 0.01 N s^2/m^2
    gravity  f = m g, g = (0, -9.81, 0) m/s^2

Classic RK4 at dt = 1e-4 s in float64 (dt / 2 moves the markers by ~1e-12 m; importing this module
turns on jax_enable_x64). The two end particles are driven: at every RK stage time t they are set
to their path p(t) and velocity p'(t).

End paths. The ends start at (-0.4, 1, 0) and (0.4, 1, 0), the rope hanging between them (a
catenary settled for 3 s with the ends fixed and an extra force -10 m v). Then p(t) = p0 + r(t)
(C(t) + D(t)) with r(t) = 1 - exp(-(t / 0.7 s)^2), so p'(0) = 0. Per axis, C (shared by both ends)
and D (one per end) are sums of three A sin(2 pi f t + phi), f uniform in 0.2-1.5 Hz, phi in
0-2 pi, A in 0.03-0.09 m (C) or a third of that (D), each A at most 0.5 m/s^2 / (2 pi f)^2; D
shrinks until the ends stay 0.55-0.85 m apart. End excursions come out at 0.1-0.2 m, marker
speeds up to ~1 m/s, segment strains 1-5 % (the hanging rope's weight alone strains it 1.5-3 %).

Observation: 12 markers on particles round(linspace(0, 55, 12)) = 0, 5, ..., 55 (markers 0 and 11
are the ends) at 100 Hz from t = 0; Gaussian noise of std 1 mm on every coordinate; 2-4 drop-outs
of 3-8 frames on random markers (all 3 coordinates NaN), never in the first or last 5 frames.
Recorded times start at a random 1-5 s. truth.json holds every setting, and the rope12 / rope34
values with the same axial stiffness, axial damping and total drag (rope12: ks.stretch +
4 ks.bend = 440 N/m, kd.stretch + 4 kd.bend = 0.14 N s/m, cd = 0.047 N s^2/m^2).
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxspring as js

jax.config.update("jax_enable_x64", True)

LENGTH, MASS, N_FINE, N_MARKERS = 1.0, 0.2, 56, 12
SEGMENT = LENGTH / (N_FINE - 1)
TRUE = dict(ks_stretch=400.0 * 55 / 11, ks_bend=50.0, kd_stretch=0.5, kd_bend=0.05, cd=0.01)
GRAVITY = (0.0, -9.81, 0.0)
DT, FPS, NOISE = 1e-4, 100, 1e-3
ANCHORS = np.array([[-0.4, 1.0, 0.0], [0.4, 1.0, 0.0]])
RAMP, SETTLE_TIME, SETTLE_DAMPING = 0.7, 3.0, 10.0
FREQUENCIES, AMPLITUDE, OWN, ACCELERATION, SEPARATION = (0.2, 1.5), (0.03, 0.09), 1 / 3, 0.5, (0.55, 0.85)
MARKER_PARTICLES = np.round(np.linspace(0, N_FINE - 1, N_MARKERS)).astype(int)
ENDS = np.array([0, N_FINE - 1])


def hanging_start(span=0.8, length=LENGTH, n=N_FINE):
    """Particles at equal arc length on the catenary of the given length between the ends, (n, 3)."""
    low, high = 1e-3, 1e3  # bisect for the catenary parameter c: 2 c sinh(span / 2c) = length
    for _ in range(200):
        c = np.sqrt(low * high)
        low, high = (c, high) if 2 * c * np.sinh(span / (2 * c)) > length else (low, c)
    s = np.linspace(-length / 2, length / 2, n)
    y = np.sqrt(c**2 + s**2) - np.sqrt(c**2 + (length / 2) ** 2)
    return np.stack([c * np.arcsinh(s / c), y, np.zeros(n)], axis=1) + ANCHORS.mean(axis=0)


def pair_forces(x, v, gap, ks, kd, rest):
    """Forces of the springs (i, i + gap) with damping along the spring, summed per particle, (N, 3)."""
    d, dv = x[gap:] - x[:-gap], v[gap:] - v[:-gap]
    length = jnp.linalg.norm(d, axis=-1, keepdims=True)
    unit = d / length
    f = (ks * (length - rest) + kd * jnp.sum(dv * unit, axis=-1, keepdims=True)) * unit
    return jnp.pad(f, ((0, gap), (0, 0))) - jnp.pad(f, ((gap, 0), (0, 0)))


def acceleration(x, v, values, damping):
    """Acceleration of every particle: springs, quadratic drag, gravity and an extra damping."""
    f = pair_forces(x, v, 1, values["ks_stretch"], values["kd_stretch"], SEGMENT)
    f += pair_forces(x, v, 2, values["ks_bend"], values["kd_bend"], 2 * SEGMENT)
    f -= values["cd"] * jnp.linalg.norm(v, axis=-1, keepdims=True) * v
    return f / (MASS / N_FINE) + jnp.asarray(GRAVITY) - damping * v


def end_motion(t, path):
    """Prescribed end positions and velocities, each (2, 3), at time t; path = (A, f, phi), each (2, 3, K)."""
    amplitude, frequency, phase = path
    w = 2 * jnp.pi * frequency
    wave = jnp.sum(amplitude * jnp.sin(w * t + phase), axis=-1)
    wave_rate = jnp.sum(amplitude * w * jnp.cos(w * t + phase), axis=-1)
    ramp, ramp_rate = 1 - jnp.exp(-((t / RAMP) ** 2)), 2 * t / RAMP**2 * jnp.exp(-((t / RAMP) ** 2))
    return ANCHORS + ramp * wave, ramp_rate * wave + ramp * wave_rate


def rk4_step(x, v, t, path, values, damping, dt):
    """One classic RK4 step; the ends are set to their path at every stage time."""

    def rate(x, v, t):
        position, velocity = end_motion(t, path)
        x, v = x.at[ENDS].set(position), v.at[ENDS].set(velocity)
        return v, acceleration(x, v, values, damping).at[ENDS].set(0.0)

    k1 = rate(x, v, t)
    k2 = rate(x + dt / 2 * k1[0], v + dt / 2 * k1[1], t + dt / 2)
    k3 = rate(x + dt / 2 * k2[0], v + dt / 2 * k2[1], t + dt / 2)
    k4 = rate(x + dt * k3[0], v + dt * k3[1], t + dt)
    x = x + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
    v = v + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    position, velocity = end_motion(t + dt, path)
    return x.at[ENDS].set(position), v.at[ENDS].set(velocity)


def rollout(x0, path, values, frames, substeps, damping=0.0, dt=DT):
    """Positions and velocities, each (frames, N, 3), at rest at x0 and then every `substeps` steps."""

    def frame(state, k):
        def step(state, j):
            return rk4_step(*state, (k * substeps + j) * dt, path, values, damping, dt), None

        state, _ = jax.lax.scan(step, state, jnp.arange(substeps), unroll=4)
        return state, state

    state = (jnp.asarray(x0), jnp.zeros_like(jnp.asarray(x0)))
    _, (x, v) = jax.lax.scan(frame, state, jnp.arange(frames - 1))
    return jnp.concatenate([state[0][None], x]), jnp.concatenate([state[1][None], v])


def settled_start(values, dt=DT):
    """The hanging rope after SETTLE_TIME s with the ends fixed and extra damping, (N, 3)."""
    still, steps = tuple(np.zeros((2, 3, 1)) for _ in range(3)), round(SETTLE_TIME / dt)
    x, _ = jax.jit(rollout, static_argnums=(3, 4))(hanging_start(), still, values, 2, steps, SETTLE_DAMPING, dt)
    return np.asarray(x[-1])


def random_path(rng, duration):
    """End path (A, f, phi), each (2, 3, 6): per end and axis three shared sinusoids, then three of its own."""

    def waves(low, high):
        shared = rng.uniform(low, high, (1, 3, 3)).repeat(2, axis=0)
        return np.concatenate([shared, rng.uniform(low, high, (2, 3, 3))], axis=-1)

    own = np.arange(6) >= 3
    frequency, phase = waves(*FREQUENCIES), waves(0.0, 2 * np.pi)
    amplitude = np.minimum(waves(*AMPLITUDE) * np.where(own, OWN, 1.0), ACCELERATION / (2 * np.pi * frequency) ** 2)
    t = np.arange(0.0, duration, 0.01)
    for _ in range(50):  # shrink the ends' own motion until their distance stays in range
        ends = np.asarray(jax.vmap(end_motion, in_axes=(0, None))(t, (amplitude, frequency, phase))[0])
        distance = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1)
        if SEPARATION[0] <= distance.min() and distance.max() <= SEPARATION[1]:
            break
        amplitude = amplitude * np.where(own, 0.8, 1.0)
    return amplitude, frequency, phase


def observe(x, rng):
    """Noisy marker positions (F, M, 3) with 2-4 drop-outs, and the gaps as (marker, first frame, length)."""
    seen = x[:, MARKER_PARTICLES] + rng.normal(0.0, NOISE, (x.shape[0], N_MARKERS, 3))
    gaps = []
    for _ in range(rng.integers(2, 5)):
        marker, length = int(rng.integers(N_MARKERS)), int(rng.integers(3, 9))
        first = int(rng.integers(5, x.shape[0] - 5 - length + 1))
        seen[first : first + length, marker] = np.nan
        gaps.append((marker, first, length))
    return seen, gaps


def axial_equivalents(values, n):
    """Values giving an n-particle rope the same axial stiffness and damping and the same total drag."""
    ratio = (n - 1) / (N_FINE - 1)  # fine over coarse spacing
    ks, kd = (round((values[f"{k}_stretch"] + 4 * values[f"{k}_bend"]) * ratio, 12) for k in ("ks", "kd"))
    return {"ks.stretch + 4 ks.bend": ks, "kd.stretch + 4 kd.bend": kd, "cd": round(values["cd"] * N_FINE / n, 12)}


def write_scene(path, n, ks, kd, cd):
    """A straight n-particle rope along x, spacing L / (n - 1), with "stretch" and "bend" spring groups."""
    x = ", ".join(f"[{i * LENGTH / (n - 1)!r}, 0.0, 0.0]" for i in range(n))
    text = f"""name = "{Path(path).stem}"
description = "A {LENGTH} m, {MASS} kg rope of {n} particles: stretch (i, i+1) and bend (i, i+2) springs."
dt = 0.001
integrator = "semi_implicit_euler"

[physics]
ks = {{ stretch = {ks[0]!r}, bend = {ks[1]!r} }}   # [N/m]
kd = {{ stretch = {kd[0]!r}, bend = {kd[1]!r} }}   # [N s/m]
cd = {cd!r}   # [N s^2/m^2], every particle
gravity = {list(GRAVITY)}

[particles]
x = [{x}]
mass = {MASS / n!r}
drag = true
"""
    for name, gap in (("stretch", 1), ("bend", 2)):
        pairs = ", ".join(f"[{i}, {i + gap}]" for i in range(n - gap))
        text += f'\n[[springs]]\nname = "{name}"\npairs = [{pairs}]\n'
    Path(path).write_text(text)


def write_experiment(path, scene, n, ks, kd, cd):
    """An experiment fitting the n-particle scene from its values; marker k on particle k (n - 1) / 11."""
    init = f'{{ "ks.stretch" = {ks[0]!r}, "kd.stretch" = {kd[0]!r}, "ks.bend" = {ks[1]!r}, cd = {cd!r} }}'
    Path(path).write_text(f"""scene = "{scene}"
[target]
recordings = ["train/*.h5"]
markers = {list(range(0, n, (n - 1) // (N_MARKERS - 1)))}     # particle carrying marker k
driven = [0, {n - 1}]                 # PARTICLE indices moved as their markers were recorded
start = 5
smooth = 5                            # start states and driven paths from 11-frame quadratic fits
[fit]
params = ["ks.stretch", "kd.stretch", "ks.bend", "cd"]
tolerance = 1e-6                      # noisy markers: a 1e-6 relative gain over 6 iterations is done
init = {init}
[evaluate]
recordings = ["held_out/*.h5"]
""")


def write_fit_files(out):
    """rope12/rope34 scenes and experiments; rope34 keeps rope12's ks l and kd l per spring and its total drag."""
    files = []
    for n, values in ((12, ((300.0, 1.0), (0.05, 0.01), 0.02)), (34, ((900.0, 3.0), (0.15, 0.03), 0.02 * 12 / 34))):
        files += [out / f"rope{n}.toml", out / f"rope{n}_experiment.toml"]
        write_scene(files[-2], n, *values)
        write_experiment(files[-1], files[-2].name, n, *values)
    return files


def make_rope_recordings(out_dir, train=8, held_out=4, seed=0, frames=500, values=None, dt=DT):
    """Simulate train + held_out recordings; write them, the fit's scenes and truth.json under out_dir.

    Recording k (train first, then held out) draws its end paths, noise, drop-outs and time
    offset from numpy seed [seed, k]. `values` overrides entries of TRUE.

    Returns:
        dict (also in truth.json) of the true values, the generator settings, rope12/rope34
        values with the same axial stiffness, damping and drag, sanity numbers, per recording
        its file, seed, gaps (marker, first frame, length) and sanity numbers; and "files".

    Example:
        >>> truth = make_rope_recordings("/tmp/rope", train=2, held_out=1)
    """
    out, values = Path(out_dir), {**TRUE, **(values or {})}
    rngs = [np.random.default_rng([seed, k]) for k in range(train + held_out)]
    paths = [random_path(rng, frames / FPS) for rng in rngs]
    batch = tuple(np.stack([p[i] for p in paths]) for i in range(3))
    simulate = jax.jit(jax.vmap(rollout, in_axes=(None, 0, None, None, None, None, None)), static_argnums=(3, 4))
    x, v = simulate(settled_start(values, dt), batch, values, frames, round(1 / (FPS * dt)), 0.0, dt)
    x, v = np.asarray(x), np.asarray(v)
    strain = np.linalg.norm(np.diff(x, axis=2), axis=-1) / SEGMENT - 1
    speed = np.linalg.norm(v[:, :, MARKER_PARTICLES], axis=-1).max(axis=(1, 2))
    excursion = np.linalg.norm(x[:, :, ENDS] - ANCHORS, axis=-1).max(axis=1)
    records = []
    for k, rng in enumerate(rngs):
        file = out / ("train" if k < train else "held_out") / f"rope_{k if k < train else k - train:03d}.h5"
        file.parent.mkdir(parents=True, exist_ok=True)
        markers, gaps = observe(x[k], rng)
        t = rng.uniform(1.0, 5.0) + np.arange(frames) / FPS
        js.save_recording(file, js.Recording(t=t, x=markers, markers=[f"m{i}" for i in range(N_MARKERS)]))
        stats = dict(max_speed=float(speed[k]), max_strain=float(strain[k].max()), excursion=excursion[k].tolist())
        records.append(dict(file=str(file.relative_to(out)), seed=[seed, k], t0=float(t[0]), gaps=gaps) | stats)
    truth = dict(values=values, gravity=GRAVITY, particles=N_FINE, length=LENGTH, mass=MASS, integrator="rk4", dt=dt)
    truth |= dict(fps=FPS, frames=frames, noise_std=NOISE, marker_particles=MARKER_PARTICLES.tolist(), seed=seed)
    truth |= dict(axial_equivalents={f"rope{n}": axial_equivalents(values, n) for n in (12, 34)})
    truth |= dict(min_strain=float(strain.min()), max_strain=float(strain.max()), max_marker_speed=float(speed.max()))
    truth |= dict(recordings=records)
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    truth["files"] = [out / r["file"] for r in records] + [out / "truth.json"] + write_fit_files(out)
    return truth


def main(argv=None):
    """Command line: write the recordings, scenes and truth.json, and say what was written."""
    parser = argparse.ArgumentParser(description="Write rope recordings from an independent, finer rope model.")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--train", type=int, default=8, help="training recordings (default 8)")
    parser.add_argument("--held-out", type=int, default=4, help="held-out recordings (default 4)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=500, help="frames per recording at 100 Hz (default 500)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    truth = make_rope_recordings(args.out, args.train, args.held_out, args.seed, args.frames)
    print("\n".join(str(file) for file in truth["files"]))
    print(f"max marker speed {truth['max_marker_speed']:.2f} m/s, segment strain {truth['min_strain']:.4f}", end="")
    print(f" to {truth['max_strain']:.4f}; took {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
