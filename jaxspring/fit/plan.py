"""The plan of a fit: its stages, and the two transitions that change it while it runs.

A fit runs a list of `Stage`s (`plan_stages`: direct, curriculum, shooting, ensemble, segment
states; see `FitSettings.strategy`). Two measurements taken while it runs change the list, and
nothing else does:

- `before_final`, when the fit reaches the plan's final stage: the horizon cut. A final stage
  over the whole target after shorter ones is fitted only over the frames its misfit stays
  smooth over (`fit.horizon.measure_horizon`, `horizon_stage`); and where that stage would be
  longer segments from noisy recorded states, the noisy refit in their place (`refit_from`).
- `after_last`, when the plan is done: the noisy refit after it. Recorded states whose
  positions are noisy, with an answer that leaves more misfit than their noise: a
  "position_shooting" stage fits the segments' start positions too.

The plan is kept in `FitProgress.plan` and saved with it, so a resumed fit runs the same stages.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import InputError
from ..sim.scene import Scene
from .gradient import best_of_stages, step_function
from .horizon import measure_horizon
from .objective import loss_function
from .observations import Observations
from .position_shooting import start_fitted_noise
from .progress import FitProgress
from .settings import ENSEMBLE_MAX_PARAMETERS, SEGMENT_STATES, FitSettings, Stage
from .shooting import touching
from .stages import FitRun

PLAN_VERSION = 5
"""The rules by which a fit's stages are planned, added and ended (`plan_stages`, the
transitions `before_final` and `after_last`), numbered: a fit file keeps stage indices and the
plan, so `--resume` refuses a file written under other rules. 2: "position_shooting" replaces a final
stage of longer segments from noisy recorded states instead of following it. 3: a
"shooting" stage on exact data ends with Levenberg-Marquardt steps
(`least_squares.finish_segments`). 4: optimizer "auto" runs the whole-take stages of
recordings with Levenberg-Marquardt (`least_squares.lm_step_function`). 5: the plan is saved with the progress (`FitProgress.plan`)
and a resumed fit runs the saved one."""


def plan_stages(
    observations: Observations, settings: FitSettings, scene: Scene | None = None, values: int = 1
) -> list[Stage]:
    """The stages a fit of `values` scalar parameter values runs through (see FitSettings.strategy, .ensemble)."""
    total = observations.frame_count - 1
    strategy = settings.strategy
    rough = _touches_ground(scene, observations)
    if strategy == "auto":
        if getattr(observations, "shootable", False):
            # recordings: driven, damped motion from estimated start states; short segments
            # from noisy states bias the fit and a curriculum's early stages crawl along
            # what the data do not determine (measured on rope recordings), so fit the whole take
            strategy = "direct"
        elif observations.steps <= settings.long_horizon_steps and not rough:
            strategy = "direct"
        else:
            strategy = "shooting" if observations.full else "curriculum"
    if strategy == "shooting" and not _shootable(observations):
        raise InputError(
            "strategy",
            "multiple shooting from recorded states needs full recorded states of every particle",
            "use free_shooting (fits the segments' states from positions) or curriculum",
        )
    if strategy == "free_shooting":
        if getattr(observations, "shootable", False):
            raise InputError(
                "strategy", "free_shooting fits target files, not recordings", 'fit recordings with "direct"'
            )
        return [Stage("free_shooting", min(settings.segment_frames, total))]
    if strategy == "position_shooting":  # shooting brings the values near, then the starts' positions are fitted
        if not observations.full:
            raise InputError(
                "strategy",
                "position_shooting starts from recorded states and needs them for every particle",
                "use free_shooting (fits the segments' states from positions)",
            )
        frames = min(settings.segment_frames, total)
        return [Stage("shooting", frames), Stage("position_shooting", frames)]
    if strategy == "shooting":  # from recorded states
        stages = [Stage("shooting", min(settings.segment_frames, total)), Stage("direct", total)]
    elif strategy == "curriculum":
        horizons = sorted({max(2, min(total, math.ceil(total * f))) for f in (0.125, 0.25, 0.5, 1.0)})
        stages = [Stage("direct", h) for h in horizons]
    else:
        stages = [Stage("direct", total)]
    ensemble = settings.ensemble == "ensemble" or (
        settings.ensemble == "auto" and rough and values <= ENSEMBLE_MAX_PARAMETERS
    )
    if ensemble:
        if values > ENSEMBLE_MAX_PARAMETERS:
            raise InputError(
                "ensemble",
                f"the ensemble stage takes at most {ENSEMBLE_MAX_PARAMETERS} parameter values, not {values}",
                'fit scalar parameters, or set ensemble = "gradient"',
            )
        stages[-1] = Stage("ensemble", total)
    return stages


def needs_horizon(stages: list[Stage], observations: Observations) -> bool:
    """Whether the plan's final stage is to be fitted to the horizon its misfit stays smooth
    over (`over_horizon`): shorter stages came first (multiple shooting from recorded
    states, or a curriculum's shorter horizons), and the final stage still spans the whole
    target from its initial state. Not for recordings (driven, each from its own start
    state): they are fitted over their whole takes.

    Example:
        >>> needs_horizon([Stage("shooting", 10), Stage("ensemble", 250)], observations)  # True
    """
    return (
        not getattr(observations, "shootable", False)
        and len(stages) > 1
        and stages[0].kind in ("shooting", "direct")
        and stages[-1].kind in ("direct", "ensemble")
    )


def over_horizon(stage: Stage, horizon: int, recorded: bool = True, segment_frames: int = 10) -> Stage:
    """The final stage `stage` (over the whole target) when `horizon` frames cover the
    target; else, with `recorded` states, multiple shooting from them with the longest equal
    segments of at most `horizon` frames (the optimiser on a misfit smooth at the measured
    scale; fewer trailing frames left out than there are segments), and from positions
    alone multiple shooting with fitted segment states ("free_shooting", segments of
    `segment_frames` frames, or `horizon` if shorter).

    Example:
        >>> over_horizon(Stage("ensemble", 250), 62)  # Stage("shooting", 50): 5 segments
    """
    total = stage.frames
    if horizon >= total:
        return stage
    horizon = max(int(horizon), 1)
    if recorded:
        return Stage("shooting", total // math.ceil(total / horizon))
    return Stage("free_shooting", min(int(segment_frames), horizon))


def _shootable(observations) -> bool:
    return bool(observations.full or getattr(observations, "shootable", False))


def _touches_ground(scene: Scene | None, observations: Observations) -> bool:
    """Whether the target reaches the ground plane (contact makes the loss landscape rough)."""
    if scene is None or not scene.model.has("ground"):
        return False
    return bool(np.nanmin(observations.x[..., 1]) < float(scene.params.ground_height))


def horizon_stage(scene: Scene, observations: list, names, settings: FitSettings, stage: Stage, horizon: int) -> Stage:
    """A plan's final `stage` fitted to a measured `horizon` [frames] (`over_horizon`) for
    these targets. Free shooting (from positions alone) only where it can do as well: every
    free particle observed (else each segment's unseen states would be fitted from far fewer
    data than the whole horizon's known start determines them) and every target with a
    segment clear of the ground (else there is nothing to fit); where not, the whole
    horizon, which the report then calls not smooth.

    Example:
        >>> horizon_stage(scene, [obs], ["ks"], js.FitSettings(), Stage("ensemble", 250), 62)
    """
    final = over_horizon(stage, horizon, observations[0].full, settings.segment_frames)
    if final is stage and stage.kind == "ensemble" and horizon >= stage.frames:
        # the misfit was measured smooth at the horizon's spread: a wider cloud would only
        # average over motions the answer is already known not to have
        return dataclasses.replace(stage, spread=min(settings.horizon_spread, settings.ensemble_spread))
    if final.kind == "free_shooting":
        free = np.nonzero(~np.asarray(scene.model.pinned))[0]
        seen = all(np.isin(free, o.particles).all() for o in observations)
        if not seen or any(touching(scene, o, final.frames, names).all() for o in observations):
            return stage
    return final


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


def initial_plan(run: FitRun, progress: FitProgress, planned: list[Stage]) -> list[Stage]:
    """The plan a fit runs: the saved one of a resumed fit (`progress.plan`), else the
    `planned` stages (`plan_stages`), with the transitions a progress made by hand already
    records (its measured horizon, its noisy refit) applied.

    Example:
        >>> initial_plan(run, progress, plan_stages(obs, settings, scene))  # [Stage("shooting", 10), ...]
    """
    if progress.plan is not None:
        return list(progress.plan)
    stages = list(planned)
    if progress.horizon is not None and needs_horizon(stages, run.reference):
        stages[-1] = horizon_stage(run.scene, run.observations, run.names, run.settings, stages[-1], progress.horizon)
    if progress.refit_frames is not None:
        refit_stages(stages, progress.refit_frames)
    return stages


def before_final(run: FitRun, progress: FitProgress) -> bool:
    """The transition when a fit reaches the final stage of a plan that needs its horizon
    (`needs_horizon`): the horizon measured once at the answer so far (a resumed fit reads
    it) and the final stage fitted over it (`horizon_stage`); then, where that stage is
    longer segments from noisy recorded states, the noisy refit in their place
    (`refit_from`). Sets a new `progress.plan` (and, refitting, `progress.theta`); again
    on a resumed fit, it changes nothing more. Returns whether it refitted (a
    checkpoint keeps the decision)."""
    stages = list(progress.plan)  # a new list: a progress kept before keeps its plan
    if progress.stage != len(stages) - 1 or not needs_horizon(stages, run.reference):
        return False
    if progress.horizon is None:
        spread = run.settings.horizon_spread
        progress.horizon = measure_horizon(run.scene, run.observations, run.names, spread, progress.theta)
    stages[-1] = horizon_stage(run.scene, run.observations, run.names, run.settings, stages[-1], progress.horizon)
    progress.plan = stages
    start = refit_from(
        run.scene, run.observations, run.names, run.settings, stages, progress, run.data, before_final=True
    )
    if start is None:
        return False
    progress.theta, progress.refit_frames = start, stages[0].frames
    refit_stages(stages, progress.refit_frames)
    return True


def after_last(run: FitRun, progress: FitProgress) -> None:
    """The transition when a plan is done: where the recorded states' positions are noisy and
    its answer leaves more misfit than their noise (`refit_from`), a "position_shooting" stage
    from that answer is added (`refit_stages`) and the fit goes on (once)."""
    if progress.refit_frames is not None:
        return
    start = refit_from(run.scene, run.observations, run.names, run.settings, progress.plan, progress, run.data)
    if start is not None:
        progress.theta, progress.refit_frames, progress.done = start, progress.plan[0].frames, False
        progress.plan = list(progress.plan)
        refit_stages(progress.plan, progress.refit_frames)
