"""Fit settings and the plan of stages a fit runs (direct, curriculum, shooting, ensemble)."""

from __future__ import annotations

import dataclasses
import math

from ..errors import InputError
from ..sim.params import NON_NEGATIVE

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
            segments' start positions too ("position_shooting", `fit.plan.refit_from`).
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
