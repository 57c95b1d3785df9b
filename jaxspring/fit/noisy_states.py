"""Recorded states whose positions are noisy: whether a plan's answer explains the data to
their noise, and where not, a stage that fits the segments' start positions too."""

from __future__ import annotations

import numpy as np

from ..sim.scene import Scene
from .gradient import best_of_stages, step_function
from .objective import loss_function
from .position_shooting import start_fitted_noise
from .progress import FitProgress
from .settings import SEGMENT_STATES, FitSettings, Stage

NOISE_FREE = 1e-4
"""Recorded positions whose noise (`start_fitted_noise`) has an RMS below this fraction of the
target's RMS displacement count as noise-free (round-off, float32 files): `refit_from`
leaves their fit as it is."""

MISFIT_OVER_NOISE = 1.1
"""An answer whose misfit exceeds the noise variance (`start_fitted_noise`) by more than this
factor, and by more than three standard deviations of that estimate, does not explain the
data: with 1% noise on the 7 x 6 x 5 jelly over 1 s, answers in wrong dips of the whole
horizon's misfit left 1.24x and 1.77x, a good one 1.00x."""


def refit_from(
    scene: Scene,
    observations: list,
    names,
    settings: FitSettings,
    stages: list[Stage],
    progress: FitProgress,
    data,
    before_final: bool = False,
) -> dict | None:
    """Where a plan on recorded states whose positions are noisy goes on to fit the segments'
    start positions ("position_shooting"), or None where it ends as planned.

    It goes on when "auto" ran multiple shooting from recorded states, and for some member
    (then the whole batch goes on) the plan's answer (`best_of_stages`) leaves more misfit
    on the objective below than the positions' noise variance allows: more than
    `MISFIT_OVER_NOISE` times it plus three standard deviations of its estimate, the noise
    being above `NOISE_FREE`. The objective is the final stage's, asked once the plan is
    done, where that stage does not start from the recorded states (the whole horizon);
    where it would be longer segments from them (`over_horizon`), it is asked
    `before_final` that stage, at the shooting stage's answer, on the shooting stage's
    objective: segments from noisy states leave their starts' noise in
    their misfit whatever their length, so the longer segments would be refitted after
    they ran; the fit goes on in their place (`refit_stages`). The noise variance is
    measured at the answer by fitting the start positions of a few segments
    (`start_fitted_noise`). Returns the answer (log values per member), which the new stage
    starts from.

    What it catches: segments from noisy recorded states leave their starts' noise in their
    misfit (1.3-1.5x the noise on the 7 x 6 x 5 jelly over 1 s with 1% noise, at any answer)
    and bias the damping; a whole horizon's misfit over several impacts has dips whose
    answers leave more than the noise (that jelly: kd 7x and 22x its truth at 1.24x and
    1.77x the noise, with standard errors of 0.02%); and a real recording's noisy first
    frame makes a whole-horizon stage from it leave more than the noise too. A whole-horizon
    answer that leaves the noise (the 0.7 s jelly) is kept, at the cost of the measurement
    (1.3 s of that jelly's 18 s fit).

    Example:
        >>> refit_from(scene, [obs], names, settings, [Stage("shooting", 10), Stage("ensemble", 100)], progress, data)
    """
    if settings.strategy != "auto" or stages[0].kind != "shooting" or stages[-1].kind in SEGMENT_STATES:
        return None
    if before_final != (stages[-1].kind == "shooting"):  # before longer segments from the states, else after
        return None
    objective = stages[0] if before_final else stages[-1]
    value = step_function(loss_function(scene, observations[0], names, objective), settings, len(observations) > 1)[2]
    theta, losses = best_of_stages(progress, names, value, data)
    for member, loss in enumerate(losses):
        target = observations[member if len(observations) > 1 else 0]
        x = np.asarray(target.x, dtype=float)
        floor = (NOISE_FREE * float(np.sqrt(np.mean((x - x[:1]) ** 2)))) ** 2
        if not loss > MISFIT_OVER_NOISE * floor:
            continue
        values = {n: np.exp(np.asarray(theta[n][member], dtype=float)) for n in names}
        variance, freedom = start_fitted_noise(scene, target, names, values, stages[0].frames)
        if variance > floor and loss > variance * (MISFIT_OVER_NOISE + 3 * np.sqrt(2 / freedom)):
            return theta
    return None


def refit_stages(stages: list[Stage], frames: int) -> None:
    """Add the "position_shooting" stage `refit_from` chose to the plan (in place): in place
    of a final stage of longer segments from the recorded states (decided before it), else
    after the final stage. A resumed fit rebuilds its plan the same way (`PLAN_VERSION`).

    Example:
        >>> stages = [Stage("shooting", 10), Stage("shooting", 33)]
        >>> refit_stages(stages, 10)  # stages: shooting 10, position_shooting 10
    """
    if stages[-1].kind == "shooting":
        stages[-1] = Stage("position_shooting", frames)
    else:
        stages.append(Stage("position_shooting", frames))


def why_refit(stages: list[Stage], progress: FitProgress, horizon_words: str) -> str:
    """Why the final segment-state stage was chosen, in words (after its objective)."""
    measured = f"{horizon_words}; " if progress.horizon is not None else ""
    if progress.refit_frames is not None:
        before = stages[-2]
        who = "of a member of this batch " if np.shape(progress.theta[next(iter(progress.theta))])[0] > 1 else ""
        return (
            f" ({measured}the answer {who}of the {before.kind} stage over {before.frames} frames left more misfit"
            " than the recorded positions' noise: their starts were fitted too)"
        )
    return f" ({horizon_words})" if progress.horizon is not None else ""
