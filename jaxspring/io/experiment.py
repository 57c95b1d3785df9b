"""Identification experiments: TOML files naming a scene, a target, what to fit and how."""

from __future__ import annotations

import dataclasses
import glob
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..fit.observations import Observations, observations_from_trajectory, synthetic_observations
from ..fit.recordings import LOSSES, RecordingTarget, recording_target
from ..fit.settings import FitSettings
from ..sim.scene import Scene
from . import schema
from .recording import load_recording
from .scene import load_scene, resolve_scene_path
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
        true_values: parameters of the synthetic target (default: the scene's own); with a
            target file, the truth the experiment declares (else the file's values are shown
            as "file values", not as the truth).
        steps, save_every: length and frame stride of the synthetic target.
        noise: observation noise of the synthetic target, relative to the RMS displacement.
        seed: random seed of the noise.
        particles: observed particles (None: every free particle).
        recordings: recording files to fit (the fitted values are shared by all of them).
        markers, driven, start, smooth, fit_start, fit_driven: how recordings map onto the
            scene and whether their start states and driven paths are fitted too (see
            `recording_target`).
        loss, huber_scale: the recordings' misfit ("mse", "l1" or "huber").
        evaluate: held-out recording files whose error `jaxspring fit` reports after fitting.

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
    recordings: tuple = ()
    markers: list | None = None
    driven: tuple = ()
    start: int = 1
    smooth: int = 0
    fit_start: bool = False
    fit_driven: bool = False
    velocities: bool = True
    loss: str = "mse"
    huber_scale: float = 0.002
    evaluate: tuple = ()
    scene_text: str = ""

    def replace(self, **changes) -> Experiment:
        return dataclasses.replace(self, **changes)

    def observations(self) -> Observations | RecordingTarget:
        """The target: the recordings, the recorded file, or a synthetic recording with noise."""
        if self.recordings:
            return self.recording_target(self.recordings)
        if self.target_file is not None:
            observations = observations_from_file(self.scene, self.target_file, self.particles)
            if self.true_values:  # the experiment declares the truth
                truth = {k: np.asarray(v) for k, v in self.true_values.items()}
                observations = dataclasses.replace(observations, truth=truth, truth_label="true")
        else:
            observations = synthetic_observations(
                self.scene, self.true_values or {}, self.steps, self.save_every, self.noise, self.seed, self.particles
            )
        # positions only, as a camera records them: no start states for multiple shooting
        return observations if self.velocities else dataclasses.replace(observations, states=None)

    def recording_target(self, paths) -> RecordingTarget:
        """`paths` (recording files) prepared with this experiment's markers, driven and start."""
        loaded = [load_recording(p) for p in paths]
        try:
            return recording_target(
                self.scene,
                loaded,
                self.markers,
                self.driven,
                self.start,
                self.smooth,
                self.loss,
                self.huber_scale,
                names=tuple(Path(p).stem for p in paths),
                fit_start=self.fit_start,
                fit_driven=self.fit_driven,
            )
        except InputError as exc:
            raise exc.within("", "target") from None


def recording_paths(patterns, base: Path, field: str) -> tuple:
    """Files matching `patterns` (paths or globs, relative to `base`), sorted, each once."""
    found, seen = [], set()
    for pattern in patterns:
        full = pattern if Path(pattern).is_absolute() else str(base / pattern)
        matches = sorted(glob.glob(full)) if glob.has_magic(pattern) else ([full] if Path(full).exists() else [])
        if not matches:
            raise InputError(field, f"{pattern!r} matches no file (looked in {base})", "fix the path or glob")
        for m in matches:  # one file under two names (a glob and a path, a link) counts once
            if Path(m).resolve() not in seen:
                found.append(m)
                seen.add(Path(m).resolve())
    return tuple(found)


def observations_from_file(scene: Scene, path, particles=None) -> Observations:
    """Observations from a trajectory file, checked against `scene`; the file's own params are
    kept as reference values (`truth_label` "file": what the file was written with, which an
    independent recording of the same scene need not share)."""
    recorded, trajectory = load_trajectory(path)
    if recorded.model.particle_count != scene.model.particle_count:
        raise InputError(
            "target",
            f"{path} has {recorded.model.particle_count} particles but the scene has {scene.model.particle_count}",
            "give a target recorded from this scene",
        )
    truth = recorded.model.parameter_values(recorded.params)
    try:
        observations = observations_from_trajectory(scene, trajectory, recorded.save_every, particles, truth=truth)
        return dataclasses.replace(observations, truth_label="file")
    except InputError as exc:
        raise exc.within(str(path)) from None


def load_experiment(path) -> Experiment:
    """Load and validate an experiment TOML file (see docs/file-formats.md).

    Example:
        >>> experiment = js.load_experiment("fitting/cloth.toml")
    """
    path = Path(path)
    if not path.exists():
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
    scene_text = resolve_scene_path(candidate if candidate.is_file() else scene_ref).read_text(encoding="utf-8")

    target = top.table("target", required=True)
    target_file = target.take("file", schema.string)
    if target_file is not None:
        target_file = str(path.parent / target_file)
    steps = target.take("steps", schema.count, default=scene.steps)
    save_every = target.take("save_every", schema.count, default=scene.save_every)
    noise = target.take("noise", schema.number, default=0.0)
    seed = target.take("seed", schema.count, default=0)
    particles = target.take("particles", schema.index_list)
    patterns = target.take("recordings", schema.string_list)
    markers = target.take("markers", schema.index_list)
    driven = target.take("driven", schema.index_list, default=[])
    start = target.take("start", schema.count, default=1)
    smooth = target.take("smooth", schema.count, default=0)
    fit_start = target.take("fit_start", schema.boolean, default=False)
    fit_driven = target.take("fit_driven", schema.boolean, default=False)
    velocities = target.take("velocities", schema.boolean)
    true_table = target.table("true")
    true_values = None
    if true_table is not None:
        true_values = {k: true_table.take(k, schema.non_negative_values) for k in list(true_table.data)}
    target.finish()
    recordings = ()
    if patterns is not None:
        if target_file is not None:
            raise InputError("target", "gives both file and recordings", "fit either a trajectory file or recordings")
        recordings = recording_paths(patterns, path.parent, "target.recordings")
    elif markers is not None or driven:
        raise InputError("target", "markers and driven need recordings", 'add recordings = ["takes/*.h5"]')
    if velocities is not None and patterns is not None:
        raise InputError(
            "target.velocities", "applies to a file or synthetic target (recordings hold positions only)", "remove it"
        )
    evaluate_table = top.table("evaluate")
    evaluate = ()
    if evaluate_table is not None:
        evaluate = recording_paths(
            evaluate_table.take("recordings", schema.string_list, required=True), path.parent, "evaluate.recordings"
        )
        evaluate_table.finish()
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
        horizon_spread=fit_table.take("horizon_spread", schema.number, default=defaults.horizon_spread),
        starts=fit_table.take("starts", schema.count, default=defaults.starts),
        start_spread=fit_table.take("start_spread", schema.number, default=defaults.start_spread),
    )
    backend = fit_table.take("backend", schema.string)
    loss = fit_table.take("loss", schema.string, default="mse")
    huber_scale = fit_table.take("huber_scale", schema.number, default=0.002)
    if loss not in LOSSES:
        raise InputError("fit.loss", f"unknown loss {loss!r}", f"use one of {', '.join(LOSSES)}")
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
        recordings=recordings,
        markers=markers,
        driven=tuple(driven),
        start=start,
        smooth=smooth,
        fit_start=fit_start,
        fit_driven=fit_driven,
        velocities=True if velocities is None else velocities,
        loss=loss,
        huber_scale=huber_scale,
        evaluate=evaluate,
        scene_text=scene_text,
    )
