"""What one free-shooting segment's Jacobian costs on the jelly scene (7 x 6 x 5), and why.

Free shooting (strategy "free_shooting") takes, per segment and Levenberg-Marquardt step,
the forward-mode Jacobian of the segment's frames with respect to its start state: one
tangent per state value, 1,260 for the jelly's 210 particles. This script times the
pure-JAX forward mode (`jax.jvp` through the grid stepper, tangents batched with
`jax.vmap`) of a 10-frame segment (100 steps) for several tangent batch sizes, against
one primal rollout of the same segment on the native lattice kernel (the scene's
default backend), the two run in turn so that their ratio is measured over the same
stretch of a shared machine. Medians over repeats, float64.

    python benchmarks/jacobian_cost.py [--repeats 5] [--batches 1,16,64,256,1260]

The ratio "per tangent / native primal" says how far the Jacobian is from what a native
forward-mode kernel could reach (about one primal's work per tangent).
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxspring as js  # noqa: E402
from jaxspring.bench.speed import _alternating_medians  # noqa: E402
from jaxspring.sim.state import State  # noqa: E402

STEPS, SAVE_EVERY = 100, 10


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batches", default="1,16,64,256,1260")
    args = parser.parse_args()
    scene = js.load_scene("jelly")
    x0, v0 = scene.state.x, scene.state.v
    size = x0.size

    def frames(model):
        def positions(z):
            start = State(x=x0 + z[:size].reshape(x0.shape), v=v0 + z[size:].reshape(x0.shape))
            return js.rollout(model, scene.params, start, steps=STEPS, save_every=SAVE_EVERY).x.reshape(-1)

        return positions

    zero = jnp.zeros(2 * size)
    primal = jax.jit(frames(scene.model))
    print(f"jelly segment: {STEPS} steps, {2 * size} state values; stepper {scene.model.stepper.name}")
    print(
        "| tangents | native primal | forward mode (pure JAX) | per tangent | per tangent / native primal "
        "| whole Jacobian |"
    )
    print("|---|---|---|---|---|---|")
    positions = frames(scene.model.forward_mode())
    tangents = jax.jit(jax.vmap(lambda t: jax.jvp(positions, (zero,), (t,))[1]))
    for count in (int(b) for b in args.batches.split(",")):
        basis = jnp.eye(2 * size)[:count]
        runs = [lambda: jax.block_until_ready(primal(zero)), lambda basis=basis: jax.block_until_ready(tangents(basis))]
        for run in runs:  # compile
            run()
        native, elapsed = _alternating_medians(runs, args.repeats)
        per = elapsed / count
        print(
            f"| {count} | {native * 1e3:.2f} ms | {elapsed:.3f} s | {per * 1e3:.2f} ms | {per / native:.1f}x "
            f"| {per * 2 * size:.1f} s |",
            flush=True,
        )


if __name__ == "__main__":
    main()
