"""Parameter identification: fit physical parameters by differentiating through rollouts.

The fit minimises the mean squared position error over the observed particles and
frames. Positive parameters are optimised in log space. Long targets are fitted in
stages: a horizon curriculum (short, then longer) or multiple shooting (short
segments started from recorded states) followed by a final stage over the horizon
the misfit stays smooth over (`horizon`: the whole target when it is, else segments
from recorded states as long as that), or multiple shooting with the segments' states
fitted (`shooting`). Where contact makes the loss rough, a whole-horizon last stage is
an ensemble Gauss-Newton on the loss smoothed at the scale of the parameters' own
uncertainty (see `FitSettings.ensemble`).

Modules: `loop` (fit, fit_batch: the plan's stages run one after the other), `plan` (the
stages a fit runs and the two transitions that change them), `stages` (the stage protocol and
the stage objects), `progress` (where a running fit stands), `settings` (FitSettings, Stage),
`results` (FitResult, and the results of a finished fit). The stages' pieces: `gradient`
(optimiser steps, stop rules, retreat), `least_squares` (Levenberg-Marquardt), `ensemble`,
`shooting`, `position_shooting` and `block_lm` (segments with fitted start states),
`horizon` (how long the misfit stays smooth), `search` (the start search). Targets and their
misfit: `observations`, `recordings`, `objective`, `recording_loss`. `identifiability`
(polish, standard errors), `predict`.
"""

from .horizon import Horizon, smooth_horizon
from .identifiability import Identifiability, identifiability
from .loop import fit, fit_batch
from .observations import Observations, observations_from_trajectory, synthetic_observations
from .progress import FitProgress
from .results import FitResult
from .settings import FitSettings

__all__ = [
    "FitProgress",
    "FitResult",
    "FitSettings",
    "Horizon",
    "Identifiability",
    "Observations",
    "fit",
    "fit_batch",
    "identifiability",
    "observations_from_trajectory",
    "smooth_horizon",
    "synthetic_observations",
]
