"""jaxspring: a differentiable mass-spring simulator in JAX, built for parameter identification.

The top-level namespace holds the everyday names (at most 30); the rest live in three
namespaces: `js.sim` (models, force terms, integrators, stability, device batches),
`js.io` (every reader and writer) and `js.fitting` (what fits return and the plots of
them). The code's layers are subpackages: `sim` (the physics), `steppers` (how steps run,
one per backend), `io` (files), `fit` (identification), `bench` (benchmarks), `cli`.

Example:
    >>> import jaxspring as js
    >>> scene = js.load_scene("cloth")
    >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=2000, save_every=10)
"""

import importlib as _importlib
import warnings as _warnings

from . import fitting, io, sim
from .errors import BlowUpError, FileFormatError, InputError, JaxspringError
from .fit import (
    FitResult,
    FitSettings,
    fit,
    fit_batch,
    identifiability,
    observations_from_trajectory,
    synthetic_observations,
)
from .fit.predict import predict
from .fit.recordings import recording_target
from .io.cable import cable_scene
from .io.experiment import load_experiment
from .io.recording import Recording, load_recording, save_recording
from .io.scene import builtin_scenes, load_scene, scene_from_dict
from .io.trajectory import load_trajectory, save_trajectory
from .render import render
from .sim import Params, Scene, State, Trajectory, rollout
from .version import __version__  # noqa: F401  (jaxspring.__version__)

__all__ = [
    # simulate
    "Scene",
    "load_scene",
    "scene_from_dict",
    "builtin_scenes",
    "rollout",
    "State",
    "Params",
    "Trajectory",
    # files
    "save_trajectory",
    "load_trajectory",
    "Recording",
    "load_recording",
    "save_recording",
    "load_experiment",
    # fit
    "fit",
    "fit_batch",
    "FitSettings",
    "FitResult",
    "synthetic_observations",
    "observations_from_trajectory",
    "identifiability",
    # recordings: scene, target, prediction
    "cable_scene",
    "recording_target",
    "predict",
    "render",
    # errors
    "JaxspringError",
    "InputError",
    "FileFormatError",
    "BlowUpError",
]

# Names that were top-level before the namespaces: still found, with a warning naming their place now.
_MOVED = {
    **{name: "sim" for name in sim.__all__ if name not in __all__},
    **{name: "io" for name in io.__all__ if name not in __all__},
    **{name: "fitting" for name in fitting.__all__ if name not in __all__},
}


_INTERNAL = {"smooth_horizon": "jaxspring.fit.horizon"}  # a stage's measurement, not an entry point


def __getattr__(name: str):
    if name in _MOVED:
        where = _MOVED[name]
        _warnings.warn(f"js.{name} is now js.{where}.{name}", DeprecationWarning, stacklevel=2)
        return getattr(globals()[where], name)
    if name in _INTERNAL:
        _warnings.warn(f"js.{name} is internal now: {_INTERNAL[name]}.{name}", DeprecationWarning, stacklevel=2)
        return getattr(_importlib.import_module(_INTERNAL[name]), name)
    raise AttributeError(f"module 'jaxspring' has no attribute {name!r}")
