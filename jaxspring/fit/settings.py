"""Fit settings and the plan of stages a fit runs (direct, curriculum, shooting, ensemble)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import InputError
from ..sim.params import NON_NEGATIVE
from ..sim.scene import Scene
from .observations import Observations

FITTABLE = NON_NEGATIVE  # ks, kd, cd, kg, kgd: positive, fitted in log space
OPTIMIZERS = ("auto", "lbfgs", "lm", "adam")
STRATEGIES = ("auto", "direct", "curriculum", "shooting", "position_shooting", "free_shooting")
ENSEMBLE_CHOICES = ("auto", "gradient", "ensemble")
SEGMENT_STATES = ("free_shooting", "position_shooting")  # stages fitting the segments' start states too
ENSEMBLE_MAX_PARAMETERS = 8  # scalar values; a Gaussian cloud needs several rollouts per dimension


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """How to fit.

    Attributes:
        optimizer: "auto" (default): Levenberg-Marquardt ("lm") for the whole-take stages of
            recordings (a least-squares misfit of a few values: far fewer rollouts than
            L-BFGS, docs/performance.md), L-BFGS ("lbfgs", fewest iterations on the seed
            scenes) for the rest; "lm" for every stage with a least-squares loss; or "adam".
        iterations: most iterations per stage.
        learning_rate: Adam's step in log-parameter space.
        clip: Adam's gradient clipping (global norm).
        strategy: "direct" (whole horizon at once), "curriculum" (horizons 1/8, 1/4,
            1/2, 1 of the target), "shooting" (segments of `segment_frames` frames from
            recorded states, then the whole horizon), "position_shooting" (the same
            segments, then again with their start positions fitted by Levenberg-Marquardt,
            the recorded ones counted as one more frame of data: for recorded states whose
            positions are noisy, `fit.position_shooting`), "free_shooting" (segments of
            `segment_frames` frames, each from a start state fitted with the parameters
            by Levenberg-Marquardt under a continuity penalty: positions alone suffice, and
            no simulation runs longer than a segment, so the answer minimises the
            segments' misfit, never a whole chaotic horizon's; `fit.shooting`), or "auto": direct up to
            `long_horizon_steps` steps without ground contact; beyond that, or when the
            target touches the ground, shooting when full states were recorded, else
            curriculum. After shooting, when the recorded positions are noisy and the
            plan's answer leaves more misfit than their noise, it goes on to fit the
            segments' start positions too ("position_shooting", `fit.noisy_states.refit_from`).
        segment_frames: frames per multiple-shooting segment.
        long_horizon_steps: targets longer than this count as long.
        tolerance: a stage stops when the loss falls below `tolerance**2` times its first value
            (converged to round-off) or, with L-BFGS, improves by less than this fraction over 5 iterations.
        step_tolerance: the last stage stops when no log-parameter moved by more than this in an iteration.
        warmup_step_tolerance: the same for the earlier (curriculum or shooting) stages, which only
            need to bring the parameters close.
        polish: finish with Levenberg-Marquardt (Gauss-Newton) steps on the whole horizon
            (at most `polish_iterations`; up to 64 parameter values). Scale-invariant, it
            finishes smooth, badly scaled valleys quickly; off by default because on
            contact-rough losses (the noisy jelly) it does not help. (A "shooting" stage
            on exact data is finished so whatever this says, with at most
            `polish_iterations` steps and `step_tolerance`: `fit.least_squares`.)
        ensemble: how the full-horizon stage runs. "gradient": the optimiser on the loss.
            "ensemble": Gauss-Newton on the loss smoothed over a Gaussian cloud of parameter
            values (`ensemble_members` rollouts a step, no gradients), the cloud shrinking to
            the parameters' standard errors; it steps over the small dips that contact cuts
            into the loss, where a gradient method stops. "auto" (default): "ensemble" when
            the target touches the ground and at most `ENSEMBLE_MAX_PARAMETERS` values are
            fitted, else "gradient".
        ensemble_members: rollouts per ensemble step (even; at least 4 per fitted value).
        ensemble_spread: the cloud's initial standard deviation in log-parameter space.
        horizon_spread: the final stage of a plan with earlier, shorter stages (strategy
            "shooting", "curriculum", or "auto" choosing one) fits the whole horizon only
            when the motion stays smooth over all of it when a value moves by this much in
            log space (`fit.horizon.smooth_horizon`, measured where the earlier stages
            ended): over several impacts or a chaotic spin the whole-horizon misfit is a
            landscape of dips and walls that a polish walks away from a good answer in.
            Otherwise, with recorded states, it fits the longest segments, each from its
            recorded start state, that are smooth (by the optimiser: no ensemble stage is
            needed at this scale); from positions alone, multiple shooting with fitted
            segment states ("free_shooting"; kept whole when every segment touches the
            ground). The default, 10%, is farther than a shooting answer lies from the
            truth on the seed scenes.
        starts, start_spread: with strategy "auto" on recordings and one start, the fit
            first searches for its start (`fit.search`): `starts` points between the start
            values / `start_spread` and x `start_spread` (in log space, the given start among
            them) fitted on the first eighth of the recordings, the best refitted on half,
            then kept if the whole-horizon misfit is lower there than at the given start.
            `starts` = 1 skips the search.
    """

    optimizer: str = "auto"
    iterations: int = 100
    learning_rate: float = 0.05
    clip: float = 1.0
    strategy: str = "auto"
    segment_frames: int = 10
    long_horizon_steps: int = 2000
    tolerance: float = 1e-9
    step_tolerance: float = 1e-9
    warmup_step_tolerance: float = 1e-6
    polish: bool = False
    polish_iterations: int = 20
    ensemble: str = "auto"
    ensemble_members: int = 32
    ensemble_spread: float = 0.3
    horizon_spread: float = 0.1
    starts: int = 8
    start_spread: float = 10.0

    def validate(self):
        if self.optimizer not in OPTIMIZERS:
            raise InputError(
                "optimizer", f"unknown optimizer {self.optimizer!r}", f"use one of {', '.join(OPTIMIZERS)}"
            )
        if self.strategy not in STRATEGIES:
            raise InputError("strategy", f"unknown strategy {self.strategy!r}", f"use one of {', '.join(STRATEGIES)}")
        if self.ensemble not in ENSEMBLE_CHOICES:
            raise InputError(
                "ensemble", f"unknown choice {self.ensemble!r}", f"use one of {', '.join(ENSEMBLE_CHOICES)}"
            )
        if int(self.ensemble_members) < 4 or int(self.ensemble_members) % 2:
            raise InputError("ensemble_members", "must be an even number >= 4", "set e.g. ensemble_members = 32")
        if not (math.isfinite(float(self.start_spread)) and float(self.start_spread) >= 1):
            raise InputError("start_spread", "must be a finite factor >= 1", "set e.g. start_spread = 10")
        for name in ("iterations", "segment_frames", "long_horizon_steps", "polish_iterations", "starts"):
            if int(getattr(self, name)) < 1:
                raise InputError(name, "must be >= 1", f"set a positive {name}")
        for name in (
            "learning_rate",
            "clip",
            "tolerance",
            "step_tolerance",
            "warmup_step_tolerance",
            "ensemble_spread",
            "horizon_spread",
        ):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise InputError(name, "must be a finite number > 0", f"set a positive {name}")
        return self


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of a fit over `frames` frames.

    `kind`: "direct" (the optimiser on the loss), "shooting" (segments of `frames` frames
    from recorded states), "free_shooting" (segments of `frames` frames from fitted start
    states, Levenberg-Marquardt), "position_shooting" (segments from recorded states with
    their positions fitted, Levenberg-Marquardt) or "ensemble" (smoothed Gauss-Newton, see FitSettings.ensemble).
    A "gauss_newton" stage (the optional polish, after the others) shorter than the target
    ran over segments from recorded states, as "shooting" does. `spread`: an ensemble
    stage's initial cloud (standard deviation in log-parameter space) when not
    `FitSettings.ensemble_spread`: the horizon's spread once the whole horizon was measured
    smooth at it (`fit.horizon.horizon_stage`).
    """

    kind: str
    frames: int
    spread: float | None = None


PLAN_VERSION = 4
"""The rules by which a fit's stages are planned, added and ended (`plan_stages`,
`horizon_stage`, `noisy_states.refit_stages`), numbered: a fit file keeps stage indices, so
`--resume` refuses a file written under other rules. 2: "position_shooting" replaces a final
stage of longer segments from noisy recorded states instead of following it. 3: a
"shooting" stage on exact data ends with Levenberg-Marquardt steps
(`least_squares.finish_segments`). 4: optimizer "auto" runs the whole-take stages of
recordings with Levenberg-Marquardt (`least_squares.lm_step_function`)."""


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
