"""A start search for recordings the model cannot fit exactly: many starts on a short window,
the best lengthened, and the best point on the whole horizon kept.

On recordings of a real object the smallest misfit is model error, not noise, and the
whole-horizon misfit is shaped by it: from a start far off, a gradient fit can stop in a
dip, or hardly move at all. A short window (the first eighth of every recording) is smooth
over a wide range of values and cheap, so `starts` points spread in log space around the
start values (a Latin hypercube, `start_spread` times either way per value, the given start
among them) are scored there at once as one batch, the `SEARCH_FITTED` best (a start the
time step cannot simulate scores infinity) are fitted there and again over a quarter of the
recordings; and the whole-horizon misfit decides between those points and the given start:
the short windows do not decide between the basins of the whole horizon (measured on the
cable benchmark: of two fits within 1.3% of each other on the quarter, the second was 19%
lower on the whole takes, and a fit from it ended 20% lower).
The fit proper then starts from the winner (and ends on the best point it passes through).
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from .gradient import finite_losses
from .recording_loss import loss_function, target_data
from .recordings import RecordingTarget
from .settings import Stage

SEARCH_ITERATIONS = 20
"""Iterations of each search window (the fit proper polishes afterwards)."""
SEARCH_FITTED = 2
"""Starts fitted on the short window: those whose misfit there is lowest before fitting."""
SEARCH_LOWERED = 2
"""Times the hypercube is drawn again around start values `start_spread` times lower, where
fewer than `SEARCH_FITTED` of its starts simulate on the short window."""


@dataclasses.dataclass(frozen=True)
class SearchReport:
    """What the start search did (see the module docstring).

    Attributes:
        starts: the start values tried, one dict per start (the given one first).
        window, lengthened: frames of the short and the lengthened window.
        window_loss: each start's loss on the short window [m^2] (where its fit ended, for the fitted ones).
        best: index of the start whose short-window fit won.
        given_loss, found_loss: whole-horizon loss at the given start and at the best point found.
        found: the points the search's fits ended at, and `found_losses` their whole-horizon losses.
        chosen: the values the fit proper started from; `used_search`: whether they are a point found.
        wall_s: the search's wall time [s].
        lowered: how many times the hypercube was drawn again lower (`SEARCH_LOWERED`); `starts`
            are the last one's.
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
    found: tuple = ()
    found_losses: tuple = ()
    lowered: int = 0

    def summary(self) -> str:
        """Two lines for people: what was tried and what was chosen."""
        spread = ", ".join(f"{n} {float(np.mean(v)):.4g}" for n, v in self.chosen.items())
        choice = "the search's point" if self.used_search else "the given start (the search found none better)"
        return (
            f"start search: {len(self.starts)} starts on the first {self.window} frames, the best "
            f"{SEARCH_FITTED} refitted on {self.lengthened}; whole-horizon loss {self.given_loss:.4g} at the given "
            f"start, {self.found_loss:.4g} at the search's best point\nfit started from {choice}: {spread}"
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


def _simulated(points: list[dict]) -> list[dict]:
    """The points whose every value is finite (a fit that ran into values the time step cannot simulate is dropped)."""
    return [p for p in points if all(np.all(np.isfinite(v)) for v in p.values())]


def search_start(scene, target: RecordingTarget, names, init: dict, settings, fit_batch) -> SearchReport:
    """Run the start search (module docstring) from `init` (name -> value, every name given);
    `fit_batch` fits the windows (the loop's own, handed in: the loop runs this search first)."""

    clock = time.perf_counter()
    total = target.frame_count - 1
    short = max(8, math.ceil(total / 8))
    lengthened = max(short, math.ceil(total / 4))
    quick = dataclasses.replace(settings, strategy="direct", iterations=SEARCH_ITERATIONS, polish=False, starts=1)
    plain = dataclasses.replace(target, fit_start=False, fit_driven=False)
    cut = window(plain, short)
    score = jax.jit(jax.vmap(loss_function(scene, cut, names, Stage("direct", short)), in_axes=(0, None)))
    spread, center, lowered, cut_data = float(settings.start_spread), dict(init), 0, target_data(cut)
    while True:
        starts = latin_starts(center, int(settings.starts), spread)
        logs = {n: jnp.log(jnp.stack([jnp.asarray(s[n], dtype=float) for s in starts])) for n in names}
        window_loss = finite_losses(score(logs, cut_data))
        if np.isfinite(window_loss).sum() >= min(SEARCH_FITTED, len(starts)) or lowered == SEARCH_LOWERED:
            break
        # the time step cannot simulate most starts: stiffness, damping and drag too high for
        # it; softer ones it can (a lower stiffness, damping or drag only slows the fastest motion)
        center, lowered = {n: np.asarray(v) / spread for n, v in center.items()}, lowered + 1
    chosen = [int(i) for i in np.argsort(window_loss, kind="stable")[:SEARCH_FITTED] if np.isfinite(window_loss[i])]
    found, best = [], 0
    if chosen:
        results = fit_batch(scene, [cut], names, [starts[i] for i in chosen], quick, identify=False)
        fitted_loss = finite_losses([r.loss_history[-1] for r in results])
        window_loss[chosen] = np.minimum(window_loss[chosen], fitted_loss)
        best = chosen[int(np.argmin(fitted_loss))]
        found = _simulated([{n: np.asarray(r.final[n]) for n in names} for r in results])
    if found and lengthened > short:
        longer = fit_batch(scene, [window(plain, lengthened)], names, found, quick, identify=False)
        found = _simulated([{n: np.asarray(v) for n, v in r.final.items()} for r in longer])
    whole = jax.jit(loss_function(scene, plain, names, Stage("direct", total)))
    data = target_data(plain)

    def loss(values):
        value = float(whole({n: jnp.log(jnp.asarray(values[n], dtype=float)) for n in names}, data))
        return value if math.isfinite(value) else math.inf

    points = [init, *found]
    losses = [loss(v) for v in points]
    lowest = int(np.argmin(losses))  # the given start on ties (and where nothing simulates)
    given_loss, found_loss = losses[0], min(losses[1:], default=math.inf)
    used = lowest != 0
    return SearchReport(
        starts=starts,
        window=short,
        lengthened=lengthened,
        window_loss=window_loss,
        best=best,
        given_loss=given_loss,
        found_loss=found_loss,
        chosen={n: np.asarray(v, dtype=float) for n, v in points[lowest].items()},
        used_search=bool(used),
        wall_s=time.perf_counter() - clock,
        found=tuple({n: np.asarray(v, dtype=float) for n, v in f.items()} for f in found),
        found_losses=tuple(losses[1:]),
        lowered=lowered,
    )
