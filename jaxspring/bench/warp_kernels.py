"""NVIDIA Warp kernels for the benchmark peer (imported only when `warp-lang` is installed)."""

import warp as wp


@wp.kernel
def springs(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    pairs: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=wp.float32),
    ks: wp.float32,
    kd: wp.float32,
    f: wp.array(dtype=wp.vec3),
):
    s = wp.tid()
    a = pairs[2 * s]
    b = pairs[2 * s + 1]
    d = x[b] - x[a]
    length = wp.length(d)
    u = d / length
    magnitude = ks * (length - rest[s]) + kd * wp.dot(v[b] - v[a], u)
    wp.atomic_add(f, a, magnitude * u)
    wp.atomic_sub(f, b, magnitude * u)


@wp.kernel
def integrate(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    drag: wp.array(dtype=wp.float32),
    gravity: wp.vec3,
    dt: wp.float32,
):
    i = wp.tid()
    w = inv_mass[i]
    if w == 0.0:
        v[i] = wp.vec3(0.0, 0.0, 0.0)
        return
    vel = v[i]
    force = f[i] + gravity / w - drag[i] * wp.length(vel) * vel
    vel = vel + dt * w * force
    v[i] = vel
    x[i] = x[i] + dt * vel
