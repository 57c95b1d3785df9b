"""Identification experiments: TOML files naming a scene, a target, what to fit and how."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ..errors import InputError
from ..fit.observations import Observations, observations_from_trajectory, synthetic_observations
from ..fit.settings import FitSettings
from ..sim.scene import Scene
from . import schema
from .scene import load_scene
from .trajectory import load_trajectory


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A parameter-identification experiment.

    Attributes:
        name: experiment name.
        scene: the scene whose parameters are fitted.
        params: names of the fitted parameters.
        init: start values, name -> value.
        settings: optimiser settings (FitSettings).
        target_file: a recorded trajectory file to fit, or None for a synthetic target.
        true_values: parameters of the synthetic target (default: the scene's own).
        steps, save_every: length and frame stride of the synthetic target.
        noise: observation noise of the synthetic target, relative to the RMS displacement.
        seed: random seed of the noise.
        particles: observed particles (None: every free particle).

    Example:
        >>> experiment = js.load_experiment("fitting/chain.toml")
        >>> result = js.fit(experiment.scene, experiment.observations(), experiment.params,
        ...                 init=experiment.init, settings=experiment.settings)
    """

    name: str
    scene: Scene
    params: tuple
    init: dict
    settings: FitSettings
    target_file: str | None = None
    true_values: dict | None = None
    steps: int = 1000
    save_every: int = 10
    noise: float = 0.0
    seed: int = 0
    particles: list | None = None
    description: str = ""

    def replace(self, **changes) -> Experiment:
        return dataclasses.replace(self, **changes)

    def observations(self) -> Observations:
        """The target: the recorded file, or a synthetic recording with noise."""
        if self.target_file is not None:
            return observations_from_file(self.scene, self.target_file, self.particles)
        return synthetic_observations(
            self.scene, self.true_values or {}, self.steps, self.save_every, self.noise, self.seed, self.particles
        )


def observations_from_file(scene: Scene, path, particles=None) -> Observations:
    """Observations from a trajectory file, checked against `scene`; the file's params become the known truth."""
    recorded, trajectory = load_trajectory(path)
    if recorded.model.particle_count != scene.model.particle_count:
        raise InputError(
            "target",
            f"{path} has {recorded.model.particle_count} particles but the scene has {scene.model.particle_count}",
            "give a target recorded from this scene",
        )
    truth = recorded.model.parameter_values(recorded.params)
    try:
        return observations_from_trajectory(scene, trajectory, recorded.save_every, particles, truth=truth)
    except InputError as exc:
        raise exc.within(str(path)) from None


def load_experiment(path) -> Experiment:
    """Load and validate an experiment TOML file (see docs/file-formats.md).

    Example:
        >>> experiment = js.load_experiment("fitting/cloth.toml")
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("experiment", f"file {str(path)!r} not found", "give a path to an experiment TOML file")
    document = schema.read_toml(path, "experiment")
    try:
        return _experiment_from_dict(document, path)
    except InputError as exc:
        raise exc.within(str(path)) from None


def _experiment_from_dict(document: dict, path: Path) -> Experiment:
    top = schema.Table(document, "")
    name = top.take("name", schema.string, default=path.stem)
    description = top.take("description", schema.string, default="")
    scene_ref = top.take("scene", schema.string, required=True)
    candidate = (path.parent / scene_ref).resolve()
    scene = load_scene(candidate if candidate.is_file() else scene_ref)

    target = top.table("target", required=True)
    target_file = target.take("file", schema.string)
    if target_file is not None:
        target_file = str(path.parent / target_file)
    steps = target.take("steps", schema.count, default=scene.steps)
    save_every = target.take("save_every", schema.count, default=scene.save_every)
    noise = target.take("noise", schema.number, default=0.0)
    seed = target.take("seed", schema.count, default=0)
    particles = target.take("particles", schema.index_list)
    true_table = target.table("true")
    true_values = None
    if true_table is not None:
        true_values = {k: true_table.take(k, schema.non_negative_values) for k in list(true_table.data)}
    target.finish()
    if noise < 0:
        raise InputError("target.noise", "must be >= 0", "give a relative noise level such as 0.01")
    if save_every < 1 or steps < save_every or steps % save_every:
        raise InputError(
            "target.steps", f"{steps} is not a positive multiple of save_every={save_every}", "make it one"
        )

    fit_table = top.table("fit", required=True)
    params = tuple(fit_table.take("params", schema.string_list, required=True))
    init_table = fit_table.table("init")
    init = {}
    if init_table is not None:
        init = {k: init_table.take(k, schema.non_negative_values) for k in list(init_table.data)}
    defaults = FitSettings()
    settings = FitSettings(
        optimizer=fit_table.take("optimizer", schema.string, default=defaults.optimizer),
        iterations=fit_table.take("iterations", schema.count, default=defaults.iterations),
        learning_rate=fit_table.take("learning_rate", schema.number, default=defaults.learning_rate),
        clip=fit_table.take("clip", schema.number, default=defaults.clip),
        strategy=fit_table.take("strategy", schema.string, default=defaults.strategy),
        segment_frames=fit_table.take("segment_frames", schema.count, default=defaults.segment_frames),
        long_horizon_steps=fit_table.take("long_horizon_steps", schema.count, default=defaults.long_horizon_steps),
        tolerance=fit_table.take("tolerance", schema.number, default=defaults.tolerance),
        ensemble=fit_table.take("ensemble", schema.string, default=defaults.ensemble),
        ensemble_members=fit_table.take("ensemble_members", schema.count, default=defaults.ensemble_members),
    )
    backend = fit_table.take("backend", schema.string)
    fit_table.finish()
    top.finish()
    try:
        settings.validate()
    except InputError as exc:
        raise exc.within("", "fit") from None
    if true_values:
        scene.with_params(**true_values)  # validates names, shapes and signs
    if backend is not None:
        try:
            scene = scene.with_backend(backend)
        except InputError as exc:
            raise exc.within("", "fit") from None
    return Experiment(
        name=name,
        scene=scene,
        params=params,
        init=init,
        settings=settings,
        target_file=target_file,
        true_values=true_values,
        steps=steps,
        save_every=save_every,
        noise=noise,
        seed=seed,
        particles=particles,
        description=description,
    )
