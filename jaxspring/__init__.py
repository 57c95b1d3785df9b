"""jaxspring: a differentiable mass-spring simulator in JAX, built for parameter identification.

Example:
    >>> import jaxspring as js
    >>> scene = js.load_scene("cloth")
    >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=2000, save_every=10)
"""

__version__ = "0.1.0"

from .errors import BlowUpError, FileFormatError, InputError, JaxspringError
from .io.scene import Scene, builtin_scenes, load_scene, scene_from_dict
from .io.trajectory import load_trajectory, save_trajectory
from .render import plot_fit, render
from .sim.forces import TERMS, safe_norm
from .sim.integrators import INTEGRATORS, NewtonSettings, backward_euler, rk4, semi_implicit_euler, verlet
from .sim.model import Model, check_params, make_model
from .sim.params import Params
from .sim.rollout import energy, final_state, rollout
from .sim.stability import BlowUp, StabilityEstimate, estimate_stability, find_blowup, stable_dt
from .sim.state import State, Trajectory
from .sim.topology import lattice_faces, lattice_positions, lattice_springs

__all__ = [
    "BlowUp",
    "BlowUpError",
    "FileFormatError",
    "INTEGRATORS",
    "InputError",
    "JaxspringError",
    "Model",
    "Params",
    "Scene",
    "StabilityEstimate",
    "State",
    "TERMS",
    "Trajectory",
    "builtin_scenes",
    "check_params",
    "energy",
    "estimate_stability",
    "final_state",
    "find_blowup",
    "stable_dt",
    "lattice_faces",
    "lattice_positions",
    "lattice_springs",
    "load_scene",
    "load_trajectory",
    "make_model",
    "plot_fit",
    "render",
    "rollout",
    "safe_norm",
    "save_trajectory",
    "scene_from_dict",
    "semi_implicit_euler",
    "verlet",
    "rk4",
    "backward_euler",
    "NewtonSettings",
]

from .fit import FitProgress, FitResult, FitSettings, Identifiability, fit, fit_batch, identifiability  # noqa: E402
from .fit.observations import Observations, observations_from_trajectory, synthetic_observations  # noqa: E402
from .io.experiment import Experiment, load_experiment, observations_from_file  # noqa: E402
from .io.fit_file import load_fit_progress, save_fit  # noqa: E402

__all__ += [
    "Experiment",
    "load_experiment",
    "observations_from_file",
    "load_fit_progress",
    "save_fit",
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

from .bench.accuracy import AccuracyRow  # noqa: E402
from .bench.accuracy import plot as plot_accuracy  # noqa: E402
from .bench.accuracy import read_csv as read_accuracy  # noqa: E402
from .bench.accuracy import recommend as recommend_settings  # noqa: E402
from .bench.accuracy import sweep as accuracy_sweep  # noqa: E402

__all__ += ["AccuracyRow", "accuracy_sweep", "plot_accuracy", "read_accuracy", "recommend_settings"]

from .sim.sharding import batch_mesh, shard_batch  # noqa: E402

__all__ += ["batch_mesh", "shard_batch"]
