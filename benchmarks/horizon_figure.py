"""The figure of docs/fitting.md's "final stage's horizon": why a fit of a chaotic target
ends on segments, on the jelly scene (7 x 6 x 5) spinning through 2.5 s of impacts.

Left: the nonlinearity (`jaxspring.fit.horizon.smooth_horizon`, 10% cloud) of stretches from each of the 8
recorded start states, against the stretch's length, with the limit; the horizon is where
the first curve crosses it. Right: the misfit along ks within 10% of the truth (kd at its
truth), over the whole 2.5 s and over the segments the horizon gives, each scaled to its
own largest value.

    python benchmarks/horizon_figure.py [--out docs/horizon.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxspring as js  # noqa: E402
from jaxspring.fit.horizon import NONLINEARITY_LIMIT, smooth_horizon  # noqa: E402
from jaxspring.fit.objective import loss_function, target_data  # noqa: E402
from jaxspring.fit.plan import over_horizon  # noqa: E402
from jaxspring.fit.settings import Stage  # noqa: E402

ROOT = Path(__file__).parents[1]
TRUTH = {"ks": 250.0, "kd": 0.05}


def misfit_along_ks(scene, obs, stage, offsets):
    theta = {n: jnp.full(offsets.size, np.log(v)) for n, v in TRUTH.items()}
    theta["ks"] = theta["ks"] + offsets
    loss = jax.jit(jax.vmap(loss_function(scene, obs, list(TRUTH), stage), in_axes=(0, None)))
    return np.asarray(loss(theta, target_data(obs)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "horizon.png"))
    args = parser.parse_args()
    scene = js.load_scene(ROOT / "scenes" / "jelly.toml")
    obs = js.synthetic_observations(scene, TRUTH, steps=2500, save_every=10)
    horizon = smooth_horizon(scene, obs, list(TRUTH), TRUTH)
    whole = Stage("direct", horizon.total)
    segments = over_horizon(whole, horizon.frames)
    offsets = np.linspace(-0.1, 0.1, 81)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    frames = np.arange(1, horizon.total + 1)
    for row, start in enumerate(horizon.starts):
        left.plot(frames, horizon.nonlinearity[row], lw=1, label=f"from frame {start}")
    left.axhline(NONLINEARITY_LIMIT, color="k", ls="--", lw=1, label="limit")
    left.axvline(horizon.frames, color="grey", lw=1)
    left.set(
        xlabel="stretch [frames of 10 ms]",
        ylabel="nonlinearity at 10%",
        title=f"smooth over {horizon.frames} of {horizon.total} frames",
        ylim=(0, 3 * NONLINEARITY_LIMIT),
    )
    left.legend(fontsize=7, ncol=2)
    for stage, label in (
        (whole, "whole 2.5 s"),
        (segments, f"{horizon.total // segments.frames} x {segments.frames} frames"),
    ):
        values = misfit_along_ks(scene, obs, stage, offsets)
        right.plot(100 * (np.exp(offsets) - 1), values / values.max(), label=label)
    right.set(xlabel="ks off the truth [%]", ylabel="misfit / its largest value", title="misfit along ks")
    right.legend()
    figure.suptitle("jelly 7 x 6 x 5, spinning through 2.5 s of impacts")
    figure.tight_layout()
    figure.savefig(args.out, dpi=110)
    print(f"horizon {horizon.frames} of {horizon.total} frames; final stage {segments}; wrote {args.out}")


if __name__ == "__main__":
    main()
