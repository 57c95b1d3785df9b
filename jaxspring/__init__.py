"""jaxspring: a differentiable mass-spring simulator in JAX, built for parameter identification.

Example:
    >>> import jaxspring as js
    >>> scene = js.load_scene("cloth")
    >>> traj = js.rollout(scene.model, scene.params, scene.state, steps=2000, save_every=10)
"""

__version__ = "0.1.0"

from ._errors import BlowUpError, FileFormatError, InputError, JaxspringError
from ._files import load_trajectory, save_trajectory
from ._forces import TERMS, safe_norm
from ._integrators import INTEGRATORS, NewtonSettings, backward_euler, rk4, semi_implicit_euler, verlet
from ._model import Model, check_params, make_model
from ._params import Params
from ._render import plot_fit, render
from ._rollout import energy, final_state, rollout
from ._scene import Scene, builtin_scenes, load_scene, scene_from_dict
from ._stability import BlowUp, StabilityEstimate, estimate_stability, find_blowup, stable_dt
from ._state import State, Trajectory
from ._topology import lattice_faces, lattice_positions, lattice_springs

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

from ._experiment import Experiment, load_experiment, observations_from_file  # noqa: E402
from ._fit import FitProgress, FitResult, FitSettings, Identifiability, fit, fit_batch, identifiability  # noqa: E402
from ._fit_files import load_fit_progress, save_fit  # noqa: E402
from ._observations import Observations, observations_from_trajectory, synthetic_observations  # noqa: E402

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

from ._accuracy import AccuracyRow  # noqa: E402
from ._accuracy import plot as plot_accuracy  # noqa: E402
from ._accuracy import read_csv as read_accuracy  # noqa: E402
from ._accuracy import recommend as recommend_settings  # noqa: E402
from ._accuracy import sweep as accuracy_sweep  # noqa: E402

__all__ += ["AccuracyRow", "accuracy_sweep", "plot_accuracy", "read_accuracy", "recommend_settings"]

from ._sharding import batch_mesh, shard_batch  # noqa: E402

__all__ += ["batch_mesh", "shard_batch"]
