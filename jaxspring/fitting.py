"""What a fit returns and what inspects it: `js.fitting` (the entry points, `js.fit`,
`js.fit_batch`, `js.identifiability`, `js.predict`, are top-level).

Example:
    >>> import jaxspring as js
    >>> result = js.fit(scene, target, ["ks", "kd"], {"ks": 10.0, "kd": 0.1})
    >>> js.fitting.plot_fit(result, "fit.png")
"""

from .fit.horizon import Horizon
from .fit.identifiability import Identifiability
from .fit.observations import Observations
from .fit.predict import ErrorSummary, Prediction, summarise
from .fit.progress import FitProgress
from .fit.recordings import RecordingTarget
from .render import plot_error_summary, plot_fit, plot_prediction

__all__ = [
    "Observations",
    "RecordingTarget",
    "FitProgress",
    "Horizon",
    "Identifiability",
    "Prediction",
    "ErrorSummary",
    "summarise",
    "plot_fit",
    "plot_prediction",
    "plot_error_summary",
]
