"""A start search for recordings the model cannot fit exactly: many starts on a short window,
the best lengthened, and the best point on the whole horizon kept.

On recordings of a real object the smallest misfit is model error, not noise, and the
whole-horizon misfit is shaped by it: from a start far off, a gradient fit can stop in a
dip, or hardly move at all. A short window (the first eighth of every recording) is smooth
over a wide range of values and cheap, so `starts` points spread in log space around the
start values (a Latin hypercube, `start_spread` times either way per value, the given start
among them) are scored there at once as one batch, the `SEARCH_FITTED` best (a start the
time step cannot simulate scores infinity) are fitted there, the best of them again over a
quarter of the recordings; and the whole-horizon misfit decides between that point and the
given start.
The fit proper then starts from the winner (and ends on the best point it passes through).
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from .recording_loss import loss_function, target_data
from .recordings import RecordingTarget
from .settings import Stage

SEARCH_ITERATIONS = 20
"""Iterations of each search window (the fit proper polishes afterwards)."""
SEARCH_FITTED = 2
"""Starts fitted on the short window: those whose misfit there is lowest before fitting."""


@dataclasses.dataclass(frozen=True)
class SearchReport:
    """What the start search did (see the module docstring).

    Attributes:
        starts: the start values tried, one dict per start (the given one first).
        window, lengthened: frames of the short and the lengthened window.
        window_loss: each start's loss on the short window [m^2] (where its fit ended, for the fitted ones).
        best: index of the start whose short-window fit won.
        given_loss, found_loss: whole-horizon loss at the given start and at the point found.
        chosen: the values the fit proper started from; `used_search`: whether they are the found point.
        wall_s: the search's wall time [s].
    """

    starts: list
    window: int
    lengthened: int
    window_loss: np.ndarray
    best: int
    given_loss: float
    found_loss: float
    chosen: dict
    used_search: bool
    wall_s: float

    def summary(self) -> str:
        """Two lines for people: what was tried and what was chosen."""
        spread = ", ".join(f"{n} {float(np.mean(v)):.4g}" for n, v in self.chosen.items())
        choice = "the search's point" if self.used_search else "the given start (the search found none better)"
        return (
            f"start search: {len(self.starts)} starts on the first {self.window} frames, the best (start "
            f"{self.best}) refitted on {self.lengthened}; whole-horizon loss {self.given_loss:.4g} at the given "
            f"start, {self.found_loss:.4g} at the search's point\nfit started from {choice}: {spread}"
        )


def needs_search(observations, settings, members: int) -> bool:
    """Whether `fit_batch` runs the start search: one start on recordings, strategy "auto"."""
    return (
        isinstance(observations, RecordingTarget)
        and settings.strategy == "auto"
        and int(settings.starts) > 1
        and members == 1
        and observations.frame_count - 1 >= 16
    )


def window(target: RecordingTarget, frames: int) -> RecordingTarget:
    """`target` cut to its first `frames` frames after the start frame."""
    keep = frames + 1
    return dataclasses.replace(
        target,
        times=target.times[:, :keep],
        x=target.x[:, :keep],
        filled=target.filled[:, :keep],
        states_x=target.states_x[:, :keep],
        states_v=target.states_v[:, :keep],
        lengths=np.minimum(target.lengths, keep),
    )


def latin_starts(init: dict, count: int, spread: float, seed: int = 0) -> list[dict]:
    """`count` start dicts: `init` first, then a Latin hypercube in log space, each value
    between init / spread and init * spread (every value's range cut into count - 1 strata)."""
    rng = np.random.default_rng(seed)
    names = list(init)
    draws = count - 1
    strata = np.stack([rng.permutation(draws) for _ in names], axis=1) if names else np.zeros((draws, 0))
    u = (strata + rng.uniform(size=strata.shape)) / draws  # (draws, P) in [0, 1)
    logs = (2 * u - 1) * math.log(spread)
    out = [dict(init)]
    for row in logs:
        out.append({n: np.asarray(init[n]) * math.exp(float(z)) for n, z in zip(names, row)})
    return out


def search_start(scene, target: RecordingTarget, names, init: dict, settings) -> SearchReport:
    """Run the start search (module docstring) from `init` (name -> value, every name given)."""
    from .loop import fit_batch  # the loop calls this module

    clock = time.perf_counter()
    total = target.frame_count - 1
    short = max(8, math.ceil(total / 8))
    lengthened = max(short, math.ceil(total / 4))
    quick = dataclasses.replace(settings, strategy="direct", iterations=SEARCH_ITERATIONS, polish=False, starts=1)
    starts = latin_starts(init, int(settings.starts), float(settings.start_spread))
    plain = dataclasses.replace(target, fit_start=False, fit_driven=False)
    cut = window(plain, short)
    score = jax.jit(jax.vmap(loss_function(scene, cut, names, Stage("direct", short)), in_axes=(0, None)))
    logs = {n: jnp.log(jnp.stack([jnp.asarray(s[n], dtype=float) for s in starts])) for n in names}
    window_loss = np.asarray(score(logs, target_data(cut)), dtype=float)
    window_loss = np.where(np.isfinite(window_loss), window_loss, np.inf)
    chosen = [int(i) for i in np.argsort(window_loss, kind="stable")[:SEARCH_FITTED]]
    results = fit_batch(scene, [cut], names, [starts[i] for i in chosen], quick, identify=False)
    fitted_loss = np.array([r.loss_history[-1] for r in results], dtype=float)
    fitted_loss = np.where(np.isfinite(fitted_loss), fitted_loss, np.inf)
    window_loss[chosen] = np.minimum(window_loss[chosen], fitted_loss)
    best = chosen[int(np.argmin(fitted_loss))]
    found = {n: np.asarray(results[int(np.argmin(fitted_loss))].final[n]) for n in names}
    if lengthened > short:
        longer = fit_batch(scene, [window(plain, lengthened)], names, [found], quick, identify=False)[0]
        found = {n: np.asarray(v) for n, v in longer.final.items()}
    whole = jax.jit(loss_function(scene, plain, names, Stage("direct", total)))
    data = target_data(plain)

    def loss(values):
        value = float(whole({n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names}, data))
        return value if math.isfinite(value) else math.inf

    given_loss, found_loss = loss(init), loss(found)
    used = found_loss < given_loss
    return SearchReport(
        starts=starts,
        window=short,
        lengthened=lengthened,
        window_loss=window_loss,
        best=best,
        given_loss=given_loss,
        found_loss=found_loss,
        chosen={n: np.asarray(v, dtype=float) for n, v in (found if used else init).items()},
        used_search=bool(used),
        wall_s=time.perf_counter() - clock,
    )
