"""jaxspring: a differentiable mass-spring simulator in JAX, built for parameter identification.

The public namespace holds what users call; the layers live in subpackages:
`sim` (the physics), `steppers` (how steps run, one per backend), `io` (files),
`fit` (identification), `bench` (benchmarks), `cli` (the command line).

Example:
    >>> import jaxspring as js
    >>> scene = js.load_scene("cloth")
    >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=2000, save_every=10)
"""

from .errors import BlowUpError, FileFormatError, InputError, JaxspringError
from .fit import (
    FitProgress,
    FitResult,
    FitSettings,
    Horizon,
    Identifiability,
    Observations,
    fit,
    fit_batch,
    identifiability,
    observations_from_trajectory,
    smooth_horizon,
    synthetic_observations,
)
from .fit.predict import ErrorSummary, Prediction, predict, summarise
from .fit.recordings import RecordingTarget, recording_target
from .io.cable import CableModel, cable_scene
from .io.experiment import Experiment, load_experiment, observations_from_file
from .io.fit_file import load_fit_progress, save_fit
from .io.recording import Recording, load_recording, save_recording
from .io.scene import builtin_scenes, load_scene, scene_from_dict
from .io.trajectory import load_trajectory, save_trajectory
from .render import plot_error_summary, plot_fit, plot_prediction, render
from .sim.driven import Drive
from .sim.forces import register_term, safe_norm
from .sim.integrators import (
    INTEGRATORS,
    RK4,
    BackwardEuler,
    Integrator,
    NewtonSettings,
    SemiImplicitEuler,
    Verlet,
)
from .sim.model import Model, make_model
from .sim.params import Params
from .sim.rollout import energy, final_state, rollout
from .sim.scene import Scene
from .sim.sharding import batch_mesh, shard_batch
from .sim.stability import BlowUp, StabilityEstimate, estimate_stability, find_blowup, stable_dt
from .sim.state import State, Trajectory
from .sim.topology import lattice_faces, lattice_positions, lattice_springs
from .version import __version__  # noqa: F401  (jaxspring.__version__)

__all__ = [
    # simulate
    "Scene",
    "load_scene",
    "builtin_scenes",
    "scene_from_dict",
    "Model",
    "make_model",
    "Params",
    "State",
    "Trajectory",
    "rollout",
    "Drive",
    "final_state",
    "energy",
    "safe_norm",
    "register_term",
    "lattice_springs",
    "lattice_positions",
    "lattice_faces",
    # integrators
    "Integrator",
    "SemiImplicitEuler",
    "Verlet",
    "RK4",
    "BackwardEuler",
    "NewtonSettings",
    "INTEGRATORS",
    # stability
    "estimate_stability",
    "stable_dt",
    "find_blowup",
    "StabilityEstimate",
    "BlowUp",
    # batches over devices
    "batch_mesh",
    "shard_batch",
    # files and pictures
    "save_trajectory",
    "load_trajectory",
    "Recording",
    "RecordingTarget",
    "recording_target",
    "predict",
    "cable_scene",
    "CableModel",
    "summarise",
    "ErrorSummary",
    "plot_error_summary",
    "Prediction",
    "plot_prediction",
    "load_recording",
    "save_recording",
    "render",
    "plot_fit",
    # fitting
    "fit",
    "fit_batch",
    "FitSettings",
    "FitResult",
    "FitProgress",
    "Observations",
    "observations_from_trajectory",
    "synthetic_observations",
    "observations_from_file",
    "identifiability",
    "smooth_horizon",
    "Horizon",
    "Identifiability",
    "Experiment",
    "load_experiment",
    "save_fit",
    "load_fit_progress",
    # errors
    "JaxspringError",
    "InputError",
    "FileFormatError",
    "BlowUpError",
]
