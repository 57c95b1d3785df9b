"""Peer implementations of the same semi-implicit Euler step, for `jaxspring bench speed`.

Each peer is written the way a user of that tool would write it, and checked
against jaxspring's own rollout before it is timed:
- `jax_segment_sum`: straightforward JAX, gather endpoints, `jax.ops.segment_sum` forces.
- `numpy`: vectorised NumPy, `np.bincount` to accumulate spring forces.
- `warp`: NVIDIA Warp on the CPU (optional `warp-lang`), one kernel launch each for
  springs (atomic adds) and integration per step.
Peers cover springs, drag, gravity and pinned particles (no ground): the cloth and
chain workloads.
"""

from __future__ import annotations

import numpy as np


def _arrays(scene, dtype):
    m, p = scene.model, scene.params
    return dict(
        a=np.asarray(m.springs[:, 0]),
        b=np.asarray(m.springs[:, 1]),
        rest=np.asarray(m.rest_length, dtype),
        mass=np.asarray(m.mass, dtype),
        free=~np.asarray(m.pinned),
        drag=np.asarray(m.drag),
        ks=float(p.ks),
        kd=float(p.kd),
        cd=float(p.cd) if p.cd is not None else 0.0,
        gravity=np.asarray(p.gravity if p.gravity is not None else np.zeros(3), dtype),
        dt=float(m.dt),
        x=np.asarray(scene.state.x, dtype),
        v=np.asarray(scene.state.v, dtype),
    )


def jax_segment_sum(scene, dtype=np.float32):
    """A function steps -> final positions (N, 3), compiled once per step count."""
    import jax
    import jax.numpy as jnp

    q = _arrays(scene, dtype)
    n = q["x"].shape[0]
    a, b, rest, mass = (jnp.asarray(q[k]) for k in ("a", "b", "rest", "mass"))
    free, drag, gravity = jnp.asarray(q["free"])[:, None], jnp.asarray(q["drag"])[:, None], jnp.asarray(q["gravity"])
    ks, kd, cd, dt = q["ks"], q["kd"], q["cd"], q["dt"]

    def step(state, _):
        x, v = state
        d = x[b] - x[a]
        length = jnp.sqrt(jnp.sum(d * d, axis=1, keepdims=True))
        u = d / length
        f = (ks * (length - rest[:, None]) + kd * jnp.sum((v[b] - v[a]) * u, axis=1, keepdims=True)) * u
        force = jax.ops.segment_sum(f, a, n) - jax.ops.segment_sum(f, b, n)
        force = force + mass[:, None] * gravity - cd * drag * jnp.sqrt(jnp.sum(v * v, axis=1, keepdims=True)) * v
        v = jnp.where(free, v + dt * force / mass[:, None], 0.0)
        return (x + dt * v, v), None

    cache = {}

    def run(steps):
        if steps not in cache:
            cache[steps] = jax.jit(lambda x, v: jax.lax.scan(step, (x, v), None, length=steps)[0][0])
        return np.asarray(jax.block_until_ready(cache[steps](jnp.asarray(q["x"]), jnp.asarray(q["v"]))))

    return run


def numpy_step(scene, dtype=np.float32):
    q = _arrays(scene, dtype)
    n = q["x"].shape[0]
    a, b, rest, mass, free, drag = (q[k] for k in ("a", "b", "rest", "mass", "free", "drag"))
    ks, kd, cd, dt, gravity = q["ks"], q["kd"], q["cd"], dtype(q["dt"]), q["gravity"]

    def run(steps):
        x, v = q["x"].copy(), q["v"].copy()
        for _ in range(steps):
            d = x[b] - x[a]
            length = np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
            u = d / length
            closing = np.einsum("ij,ij->i", v[b] - v[a], u)[:, None]
            f = (ks * (length - rest[:, None]) + kd * closing) * u
            force = np.stack([np.bincount(a, f[:, k], n) - np.bincount(b, f[:, k], n) for k in range(3)], axis=1)
            speed = np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
            force = force.astype(dtype) + mass[:, None] * gravity - cd * drag[:, None] * speed * v
            v = np.where(free[:, None], v + dt * force / mass[:, None], 0.0).astype(dtype)
            x = x + dt * v
        return x

    return run


def warp_available() -> bool:
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def warp_step(scene, dtype=np.float32):
    """NVIDIA Warp on the CPU, float32. Raises ImportError without `warp-lang`."""
    import warp as wp

    from . import warp_kernels as kernels

    wp.config.quiet = True
    wp.init()
    q = _arrays(scene, np.float32)
    device = "cpu"
    springs = wp.array(np.stack([q["a"], q["b"]], 1).astype(np.int32).reshape(-1), dtype=wp.int32, device=device)
    rest = wp.array(q["rest"], dtype=wp.float32, device=device)
    inv_mass = wp.array(np.where(q["free"], 1.0 / q["mass"], 0.0).astype(np.float32), dtype=wp.float32, device=device)
    drag = wp.array((q["drag"] * q["cd"]).astype(np.float32), dtype=wp.float32, device=device)
    gravity = wp.vec3(*[float(g) for g in q["gravity"]])
    count, spring_count = q["x"].shape[0], q["a"].shape[0]

    def run(steps):
        x = wp.array(q["x"], dtype=wp.vec3, device=device)
        v = wp.array(q["v"], dtype=wp.vec3, device=device)
        f = wp.zeros(count, dtype=wp.vec3, device=device)
        for _ in range(steps):
            f.zero_()
            wp.launch(
                kernels.springs, dim=spring_count, inputs=[x, v, springs, rest, q["ks"], q["kd"], f], device=device
            )
            wp.launch(kernels.integrate, dim=count, inputs=[x, v, f, inv_mass, drag, gravity, q["dt"]], device=device)
        wp.synchronize()
        return x.numpy()

    return run
