"""How noise biases a fit of recordings the model itself made: the table in docs/fitting.md.

The 6-particle rope of tests/test_recordings_fit.py (3 takes x 150 frames at 100 Hz, both
ends driven, 1 mm noise, velocities unknown), fitted from the start rule's start states and
with the start states fitted (`fit_start`), with noise on the free markers only (ends known
exactly) or on every marker. Prints each fitted value's error against the truth.

    python benchmarks/same_model_recordings.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
jax.config.update("jax_enable_x64", True)

from test_recordings_fit import ROPE, TRUTH, N, make_recordings  # noqa: E402

import jaxspring as js  # noqa: E402

INIT = {"ks.stretch": 250.0, "kd.stretch": 0.5, "cd": 0.02}


def recordings(scene, noise_on: str):
    noisy = make_recordings(scene, 3, 150, noise=1e-3)
    if noise_on == "every marker":
        return noisy
    clean = make_recordings(scene, 3, 150, noise=0.0)
    ends = np.isin(np.arange(N), [0, N - 1])[None, :, None]
    return [js.Recording(t=r.t, x=np.where(ends, c.x, r.x)) for r, c in zip(noisy, clean)]


def main() -> None:
    scene = js.scene_from_dict(ROPE)
    print("| noise on | start | " + " | ".join(TRUTH) + " | fit [s] |")
    print("|---|---|" + "---|" * (len(TRUTH) + 1))
    for noise_on in ("free markers only", "every marker"):
        recs = recordings(scene, noise_on)
        for fit_start in (False, True):
            target = js.recording_target(scene, recs, driven=[0, N - 1], start=1, smooth=5, fit_start=fit_start)
            clock = time.perf_counter()
            result = js.fit(scene, target, list(TRUTH), init=INIT, iterations=60)
            wall = time.perf_counter() - clock
            se = result.identifiability.relative_standard_error
            cells = [f"{float(result.final[n]) / TRUTH[n] - 1:+.1%} (s.e. {float(se[n]):.1%})" for n in TRUTH]
            print(
                f"| {noise_on} | {'fitted' if fit_start else 'start rule'} | " + " | ".join(cells) + f" | {wall:.0f} |"
            )


if __name__ == "__main__":
    main()
