"""Parameter identification: fit physical parameters by differentiating through rollouts.

The fit minimises the mean squared position error over the observed particles and
frames. Positive parameters are optimised in log space. Long targets are fitted in
stages: a horizon curriculum (short, then longer) or multiple shooting (short
segments started from recorded states) followed by a full-horizon stage, so the
final answer is always a full-horizon least-squares fit. Where contact makes the
loss rough, that last stage is an ensemble Gauss-Newton on the loss smoothed at the
scale of the parameters' own uncertainty (see `FitSettings.ensemble`).

Modules: `settings` (FitSettings, the plan of stages), `objective` (the misfit),
`loop` (fit, fit_batch), `ensemble` (the ensemble stage), `identifiability`
(Gauss-Newton polish, standard errors), `results`, `observations`.
"""

from .identifiability import Identifiability, identifiability
from .loop import fit, fit_batch
from .observations import Observations, observations_from_trajectory, synthetic_observations
from .results import FitProgress, FitResult
from .settings import FitSettings

__all__ = [
    "FitProgress",
    "FitResult",
    "FitSettings",
    "Identifiability",
    "Observations",
    "fit",
    "fit_batch",
    "identifiability",
    "observations_from_trajectory",
    "synthetic_observations",
]
