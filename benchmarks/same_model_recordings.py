"""How noise biases a fit of recordings the model itself made: the table in docs/fitting.md.

The 6-particle rope of tests/test_recordings_fit.py (3 takes x 150 frames at 100 Hz, both
ends driven, 1 mm noise, velocities unknown) over 10 noise seeds, fitted three ways:
noise on the free markers only (the ends' paths known exactly, as a robot reports them)
with the start states fitted (`fit_start`); noise on every marker with `fit_start`; and
noise on every marker with the driven paths fitted too (`fit_driven`). Prints, per
value, the median and largest error against the truth, the median standard error, and
the fraction of seeds within 1, 2 and 3 reported standard errors.

    python benchmarks/same_model_recordings.py [--seeds 10]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
jax.config.update("jax_enable_x64", True)

from test_recordings_fit import ROPE, TRUTH, N, make_recordings, with_exact_ends  # noqa: E402

import jaxspring as js  # noqa: E402

INIT = {"ks.stretch": 250.0, "kd.stretch": 0.5, "cd": 0.02}
CASES = {
    "free markers only (ends exact), fit_start": ("free", {"fit_start": True}),
    "every marker, fit_start": ("every", {"fit_start": True}),
    "every marker, fit_driven": ("every", {"fit_driven": True}),
}


def fit_once(scene, seed: int, noise_on: str, options: dict):
    recs = make_recordings(scene, 3, 150, noise=1e-3, seed=seed)
    if noise_on == "free":
        recs = with_exact_ends(recs, make_recordings(scene, 3, 150, noise=0.0, seed=seed))
    target = js.recording_target(scene, recs, driven=[0, N - 1], start=1, smooth=5, **options)
    clock = time.perf_counter()
    result = js.fit(scene, target, list(TRUTH), init=INIT, iterations=60)
    se = result.identifiability.relative_standard_error
    errors = {n: float(result.final[n]) / TRUTH[n] - 1 for n in TRUTH}
    return errors, {n: float(se[n]) for n in TRUTH}, time.perf_counter() - clock


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    scene = js.scene_from_dict(ROPE)
    print("| noise on, fitted | value | median error | largest error | median s.e. | within 1 / 2 / 3 s.e. | fit |")
    print("|---|---|---|---|---|---|---|")
    for label, (noise_on, options) in CASES.items():
        runs = [fit_once(scene, seed, noise_on, options) for seed in range(args.seeds)]
        wall = np.median([w for _, _, w in runs])
        for n in TRUTH:
            error = np.array([e[n] for e, _, _ in runs])
            se = np.array([s[n] for _, s, _ in runs])
            within = " / ".join(f"{np.mean(np.abs(error) <= k * se):.0%}" for k in (1, 2, 3))
            print(
                f"| {label} | {n} | {np.median(np.abs(error)):.2%} | {error[np.argmax(np.abs(error))]:+.2%} "
                f"| {np.median(se):.2%} | {within} | {wall:.0f} s |",
                flush=True,
            )


if __name__ == "__main__":
    main()
