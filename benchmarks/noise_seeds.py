"""Accuracy with observation noise over many noise seeds, never one: the table in docs/fitting.md.

Each fitting/ experiment named is fitted with 1% noise (relative to the RMS displacement)
drawn from seeds 0..S-1. Per fitted value: the median and largest error against the
truth, the median reported standard error, and the fraction of seeds within 1, 2 and 3
standard errors (an honest estimator: about 68%, 95%, 99.7%).

    python benchmarks/noise_seeds.py [--experiments mass_spring,chain] [--seeds 10] [--noise 0.01]
                                     [--dtype float64|float32] [--verbose]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

import jaxspring as js

ROOT = Path(__file__).parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", default="mass_spring,chain")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--dtype", choices=["float64", "float32"], default="float64")
    parser.add_argument("--verbose", action="store_true", help="print every seed's errors and standard errors")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", args.dtype == "float64")  # before any array is made
    print("| experiment | value | median error | largest error | median s.e. | within 1 / 2 / 3 s.e. | fit |")
    print("|---|---|---|---|---|---|---|")
    for name in args.experiments.split(","):
        errors, ses, walls = [], [], []
        for seed in range(args.seeds):
            experiment = js.load_experiment(ROOT / "fitting" / f"{name}.toml").replace(noise=args.noise, seed=seed)
            clock = time.perf_counter()
            result = js.fit(
                experiment.scene,
                experiment.observations(),
                experiment.params,
                init=experiment.init,
                settings=experiment.settings,
            )
            walls.append(time.perf_counter() - clock)
            errors.append({n: float(result.final[n]) / float(result.truth[n]) - 1 for n in experiment.params})
            ses.append({n: float(result.identifiability.relative_standard_error[n]) for n in experiment.params})
            if args.verbose:
                words = ", ".join(f"{n} {errors[-1][n]:+.2%} (s.e. {ses[-1][n]:.2%})" for n in experiment.params)
                print(f"  {name} seed {seed}: {words}, {walls[-1]:.0f} s", flush=True)
        for n in experiment.params:
            error, se = np.array([e[n] for e in errors]), np.array([s[n] for s in ses])
            within = " / ".join(f"{np.mean(np.abs(error) <= k * se):.0%}" for k in (1, 2, 3))
            print(
                f"| {name} | {n} | {np.median(np.abs(error)):.2%} | {error[np.argmax(np.abs(error))]:+.2%} "
                f"| {np.median(se):.2%} | {within} | {np.median(walls):.0f} s |",
                flush=True,
            )


if __name__ == "__main__":
    main()
