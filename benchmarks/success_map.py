"""Success map of identification over long horizons: truths drawn, starts far off, with and
without noise, each case an experiment in fitting/cases/.

For each case, draws truths (log-uniform in the case's range below) and starts (each value
1/3 to 3 times its truth, log-uniform), simulates the case's target with them (positions
only, or positions and velocities of every particle: the `_velocities` cases), with 0 or 1%
noise, and fits it as the experiment file says (free segment states for positions-only
targets with contact or long horizons; "auto" with recorded velocities: shooting, then the
final stage over the horizon the misfit stays smooth over; the cloth: "auto", which fits
its whole smooth horizon directly). A draw succeeds when every value is within 2% of the
truth (no noise) or within 3 reported standard errors (noise; the standard errors are of
the log values, so the log of fitted / true is compared). Prints the success rate, the
median fit time and the worst draw per case.

    python benchmarks/success_map.py [--draws 10] [--cases chain_10s,small_jelly_1s] [--noise 0,0.01]

Cases (fitting/cases/NAME.toml; run one as an experiment with `jaxspring fit
fitting/cases/chain_10s.toml`): the chain over 10 s (500 frames, 50 segments), the same
without spring damping, `small_jelly_1s` (a 3 x 3 x 3 jelly with the jelly scene's
springs, ground and spin, dropped from 0.3 m, landing and bouncing over 1 s), the jelly
scene itself (7 x 6 x 5, spinning, several impacts) over 1, 2.5 and 4 s with recorded
velocities, and the cloth over 2 s. Positions-only, the jelly scene is not in the map: one
10-frame segment's Jacobian (1,260 state columns) costs ~35 s per Levenberg-Marquardt step
on 2 cores, beyond the 3-minute target.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxspring as js  # noqa: E402

CASES = Path(__file__).parents[1] / "fitting" / "cases"
JELLY = {"ks": (150.0, 400.0), "kd": (0.02, 0.1)}
CHAIN = {"ks": (500.0, 2000.0), "kd": (2.0, 10.0), "cd": (0.02, 0.1)}
RANGES = {  # case -> {name: (low, high)}: the truths are drawn log-uniform in these
    "chain_10s": CHAIN,
    "undamped_chain_10s": {"ks": CHAIN["ks"], "cd": CHAIN["cd"]},
    "small_jelly_1s": JELLY,
    "jelly_1s_velocities": JELLY,
    "jelly_2.5s_velocities": JELLY,
    "jelly_4s_velocities": JELLY,
    "cloth_2s": {"ks": (2000.0, 10000.0), "kd": (0.2, 1.0), "cd": (0.001, 0.005)},
}


def draw(case: str, seed: int, noise: float):
    """(experiment, target, truth, start) of draw `seed` of `case` with relative `noise`."""
    experiment = js.load_experiment(CASES / f"{case}.toml")
    rng = np.random.default_rng(seed)
    ranges = RANGES[case]
    truth = {n: float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) for n, (lo, hi) in ranges.items()}
    start = {n: v * float(np.exp(rng.uniform(np.log(1 / 3), np.log(3)))) for n, v in truth.items()}
    target = experiment.replace(true_values=truth, noise=noise, seed=seed).observations()
    return experiment, target, truth, start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--cases", default=",".join(RANGES), help="fitting/cases/ experiments, comma-separated")
    parser.add_argument("--noise", default="0,0.01")
    parser.add_argument("--verbose", action="store_true", help="print every draw")
    args = parser.parse_args()
    print("| case | noise | success | median fit | worst |")
    print("|---|---|---|---|---|")
    for case in args.cases.split(","):
        for noise in (float(x) for x in args.noise.split(",")):
            wins, walls, worst = 0, [], 0.0
            for seed in range(args.draws):
                experiment, target, truth, start = draw(case, seed, noise)
                clock = time.perf_counter()
                result = js.fit(experiment.scene, target, experiment.params, start, experiment.settings)
                walls.append(time.perf_counter() - clock)
                error = {n: float(result.final[n]) / truth[n] - 1 for n in truth}
                se = result.identifiability.relative_standard_error  # of the log values
                # no noise: within 2%; noise: log error within 3 standard errors
                score = max(
                    abs(e) / 0.02 if noise == 0 else abs(np.log1p(e)) / (3 * float(se[n])) for n, e in error.items()
                )
                wins += score <= 1.0
                if args.verbose:
                    values = ", ".join(f"{n} {e:+.2%} (s.e. {float(se[n]):.2%})" for n, e in error.items())
                    stages = " + ".join(f"{s.kind} {s.frames}" for s in result.stages)
                    print(f"  seed {seed}: {values}, {walls[-1]:.0f} s, {score:.2g} of the bound; {stages}", flush=True)
                worst = max(worst, score)
            print(
                f"| {case} | {noise:.0%} | {wins}/{args.draws} | {np.median(walls):.0f} s | {worst:.2g} of the bound |",
                flush=True,
            )


if __name__ == "__main__":
    main()
