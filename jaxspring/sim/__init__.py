"""The physics: models, force terms, integrators, rollouts, stability and device batches.

`js.sim` holds what a user building or checking a simulation by hand calls; the most
used names (`Scene`, `State`, `Params`, `Trajectory`, `rollout`) are also top-level.

Example:
    >>> import jaxspring as js
    >>> scene = js.load_scene("chain")
    >>> js.sim.stable_dt(scene.model, scene.params, scene.state)
"""

from .driven import Drive
from .forces import register_term, safe_norm
from .integrators import INTEGRATORS, RK4, BackwardEuler, Integrator, NewtonSettings, SemiImplicitEuler, Verlet
from .model import Model, make_model
from .params import Params
from .rollout import energy, final_state, rollout
from .scene import Scene
from .sharding import batch_mesh, shard_batch
from .stability import BlowUp, StabilityEstimate, estimate_stability, find_blowup, stable_dt
from .state import State, Trajectory
from .topology import lattice_faces, lattice_positions, lattice_springs

__all__ = [
    # models and states
    "Scene",
    "Model",
    "make_model",
    "Params",
    "State",
    "Trajectory",
    "Drive",
    # force terms
    "register_term",
    "safe_norm",
    "lattice_springs",
    "lattice_positions",
    "lattice_faces",
    # time stepping
    "rollout",
    "final_state",
    "energy",
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
]
