"""Observed motion to fit: positions of some particles at some frames."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..sim.rollout import rollout
from ..sim.scene import Scene
from ..sim.state import State, Trajectory


@dataclasses.dataclass(frozen=True)
class Observations:
    """What was observed: the target of a fit.

    Attributes:
        x: observed positions [m], shape (frames, M, 3); frame k is at time k * save_every * dt.
        particles: which particles were observed, int (M,); default: every particle that is not pinned.
        save_every: time steps between frames.
        initial_state: the full state at frame 0 (known initial condition).
        states: full states (x, v of all particles) at every frame, present when every
            free particle is observed; multiple shooting starts its segments from them.
        noise_std: the observation noise's standard deviation [m] when known (synthetic targets).
        truth: the true parameter values when known (synthetic targets), name -> array.
        truth_label: what `truth` is: "true" (synthetic, or declared by the experiment) or
            "file" (the parameters a target file was written with: a reference, not the truth).

    Example:
        >>> obs = js.synthetic_observations(scene, {"ks": 1000.0}, steps=1000, save_every=10)
    """

    x: np.ndarray
    particles: np.ndarray
    save_every: int
    initial_state: State
    states: Trajectory | None = None
    noise_std: float = 0.0
    truth: dict | None = None
    truth_label: str = "true"

    @property
    def frame_count(self) -> int:
        return int(self.x.shape[0])

    @property
    def steps(self) -> int:
        return (self.frame_count - 1) * self.save_every

    @property
    def full(self) -> bool:
        """Every free particle observed and full states recorded (multiple shooting possible)."""
        return self.states is not None


def observations_from_trajectory(
    scene: Scene, trajectory: Trajectory, save_every: int, particles=None, noise_std: float = 0.0, truth=None
) -> Observations:
    """Observations of `particles` (default all) from a trajectory of `scene` saved every `save_every` steps.

    Example:
        >>> scene, traj = js.load_trajectory("recorded.h5")
        >>> obs = js.observations_from_trajectory(scene, traj, scene.save_every)
    """
    # the fit's precision, not the file's: `jaxspring run` writes float32 by default
    dtype = np.dtype(scene.model.mass.dtype)
    x = np.asarray(trajectory.x, dtype=dtype)
    velocities = np.asarray(trajectory.v, dtype=dtype)
    count = scene.model.particle_count
    if x.ndim != 3 or x.shape[1] != count:
        raise InputError(
            "target",
            f"has {x.shape[1] if x.ndim == 3 else '?'} particles but the scene has {count}",
            "give a target recorded from this scene",
        )
    if not np.all(np.isfinite(x)) or not np.all(np.isfinite(velocities)):
        raise InputError("target", "contains NaN or infinite positions", "remove or repair those frames")
    if x.shape[0] < 2:
        raise InputError("target", "has fewer than 2 frames", "record a longer trajectory")
    free = np.nonzero(~np.asarray(scene.model.pinned))[0]
    observed = free if particles is None else np.asarray(particles, dtype=np.int64).reshape(-1)
    if observed.size == 0 or observed.min() < 0 or observed.max() >= count:
        raise InputError("target.particles", f"indices must lie in 0..{count - 1}", "fix the observed particle list")
    full = np.isin(free, observed).all()
    return Observations(
        x=x[:, observed],
        particles=observed,
        save_every=int(save_every),
        initial_state=State(x=jnp.asarray(x[0]), v=jnp.asarray(velocities[0])),
        states=Trajectory(x=jnp.asarray(x), v=jnp.asarray(velocities), t=jnp.asarray(trajectory.t, dtype))
        if full
        else None,
        noise_std=float(noise_std),
        truth=truth,
    )


def synthetic_observations(
    scene: Scene,
    true_values: dict,
    steps: int,
    save_every: int,
    noise_relative: float = 0.0,
    seed: int = 0,
    particles=None,
) -> Observations:
    """Simulate a recording with `true_values` and add Gaussian observation noise.

    The noise's standard deviation is `noise_relative` times the RMS displacement
    of the observed positions from their initial positions, added to every frame
    but frame 0 (the known initial condition). Recorded full states (used to start
    multiple-shooting segments) carry the same position noise; velocities are exact.

    Example:
        >>> obs = js.synthetic_observations(scene, {"ks": 1000.0, "kd": 5.0}, 2000, 20, noise_relative=0.01)
    """
    params = scene.with_params(**true_values).params
    traj = rollout(scene.model, params, scene.state, steps=steps, save_every=save_every)
    x = np.asarray(traj.x)
    free = np.nonzero(~np.asarray(scene.model.pinned))[0]
    observed = free if particles is None else np.asarray(particles, dtype=np.int64)
    displacement = x[:, observed] - x[:1, observed]
    std = float(noise_relative) * float(np.sqrt(np.mean(displacement**2)))
    if std > 0:
        noise = np.random.default_rng(seed).normal(0.0, std, size=x.shape)
        noise[0] = 0.0
        noise[:, np.asarray(scene.model.pinned)] = 0.0
        x = x + noise
    noisy = Trajectory(x=jnp.asarray(x, dtype=traj.x.dtype), v=traj.v, t=traj.t)
    truth = {name: np.asarray(value) for name, value in scene.model.parameter_values(params).items()}
    return observations_from_trajectory(scene, noisy, save_every, particles, noise_std=std, truth=truth)
