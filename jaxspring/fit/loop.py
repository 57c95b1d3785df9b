"""The fit loop: a batch of starts and targets run through the plan's stages (`fit.plan`),
each by the stage protocol (`fit.stages`), then collected into results (`fit.results`)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..sim.scene import Scene
from ..sim.sharding import shard_batch
from .objective import check_names, target_data
from .observations import Observations
from .plan import after_last, before_final, initial_plan, plan_stages
from .progress import FitProgress
from .recording_loss import start_unknowns
from .recordings import RecordingTarget
from .results import FitResult, collect_results
from .search import needs_search, search_start
from .settings import FitSettings, Stage
from .stages import FitRun, stage_for


def fit(
    scene: Scene,
    observations: Observations,
    params=("ks", "kd"),
    init: dict | None = None,
    settings: FitSettings | None = None,
    **kwargs,
) -> FitResult:
    """Fit `params` of `scene` to `observations` by gradient-based optimisation through rollouts.

    Args:
        scene: the model and its other parameters (held fixed).
        observations: the target (see `observations_from_trajectory`, `synthetic_observations`).
        params: names to fit, e.g. ("ks", "kd", "cd").
        init: start values (name -> positive value); default: the scene's values.
        settings: a FitSettings; keyword arguments override its fields.
    Returns:
        FitResult with the fitted values, histories and the identifiability report.

    Example:
        >>> obs = js.synthetic_observations(scene, {"ks": 1000.0, "kd": 5.0, "cd": 0.05}, 1000, 10)
        >>> result = js.fit(scene, obs, ["ks", "kd", "cd"], init={"ks": 400.0, "kd": 12.0, "cd": 0.15})
        >>> print(result.table())
    """
    return fit_batch(scene, [observations], params, [init or {}], settings, **kwargs)[0]


def fit_batch(
    scene: Scene,
    observations: list[Observations],
    params=("ks", "kd"),
    inits: list[dict] | None = None,
    settings: FitSettings | None = None,
    progress: FitProgress | None = None,
    on_iteration: Callable[[FitProgress, list[Stage]], None] | None = None,
    identify: bool = True,
    max_memory: int | None = None,
    **kwargs,
) -> list[FitResult]:
    """Fit several starting guesses (multi-start) and/or several targets at once with `vmap`.

    `observations` holds one target (shared by all members) or one per member;
    `inits` one start per member (default: one member starting at the scene's values).
    Each stage's iteration is compiled up front and refused (InputError) when XLA's memory
    plan for it exceeds the memory available or `max_memory` bytes.
    `progress` continues an interrupted fit (its saved plan, `progress.plan`, is run);
    `on_iteration(progress, stages)` is called after every iteration of a stage that resumes
    exactly from there, and after every stage (the CLI checkpoints from it). With several devices in one process and a
    member count divisible by their number, the members are split across them
    (`shard_batch`); otherwise the recordings of a `RecordingTarget`, when their count
    divides by the devices' (each device simulates its share; the loss sums over all).
    The numbers are the same as on one device.

    Example:
        >>> results = js.fit_batch(scene, [obs], ["ks", "kd"], inits=[{"ks": 300.0}, {"ks": 3000.0}])
        >>> [r.final["ks"] for r in results]
    """
    settings = dataclasses.replace(settings or FitSettings(), **kwargs).validate()
    inits = list(inits) if inits else [{}]
    if len(observations) not in (1, len(inits)):
        if len(inits) == 1:
            inits = inits * len(observations)
        else:
            raise InputError(
                "observations",
                f"{len(observations)} targets for {len(inits)} starts",
                "give one target or one per start",
            )
    names = tuple(params)
    for init in inits:
        check_names(scene, names, init)
    members = len(inits)
    shapes = [o.x.shape for o in observations]
    if len(set(shapes)) != 1:
        raise InputError(
            "observations", f"targets differ in shape {shapes}", "give targets of equal length and particles"
        )
    reference = observations[0]
    batched_data = len(observations) > 1
    if batched_data:
        data = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[target_data(o) for o in observations])
    else:
        data = target_data(reference)
    present = scene.model.parameter_values(scene.params)
    start_values = [{n: jnp.asarray(init.get(n, present[n]), dtype=float) for n in names} for init in inits]
    # the start values' shape decides what is fitted: one value, or one per spring (particle)
    try:
        shapes = {n: np.broadcast_shapes(present[n].shape, *(s[n].shape for s in start_values)) for n in names}
    except ValueError:
        raise InputError("init", "start values of different shapes", "give each parameter one shape") from None
    scene.with_values({n: np.ones(shapes[n]) for n in names})  # a shape the parameter cannot take is an InputError
    planned = plan_stages(reference, settings, scene, values=sum(math.prod(shapes[n]) for n in names))
    search = None
    if progress is None and needs_search(reference, settings, members):  # recordings: find a start first
        search = search_start(scene, reference, names, start_values[0], settings, fit_batch)
    if progress is None:
        first = [search.chosen] if search else start_values
        theta = {n: jnp.stack([jnp.log(jnp.broadcast_to(jnp.asarray(s[n]), shapes[n])) for s in first]) for n in names}
        for key, value in start_unknowns(reference).items():  # a fitted start state (recordings)
            theta[key] = jnp.broadcast_to(value, (members,) + value.shape)
        progress = FitProgress(0, 0, theta, None, [], {n: [] for n in names}, [])
        progress.wall_s = search.wall_s if search else 0.0
    # members across the devices of one process; across processes, each member's values would
    # live on one process only (the recordings are split across processes instead)
    members_sharded = jax.process_count() == 1 and jax.device_count() > 1 and members % jax.device_count() == 0
    if members_sharded:  # members across devices
        progress.theta = shard_batch(progress.theta)
        if batched_data:
            data = shard_batch(data)
    elif jax.device_count() > 1 and isinstance(reference, RecordingTarget) and not batched_data:
        if len(reference.names) % jax.device_count() == 0:  # recordings across devices
            data = shard_batch(data)
    run = FitRun(
        scene, observations, names, settings, data, batched_data, members, members_sharded, max_memory, on_iteration,
        time.perf_counter() - progress.wall_s,
    )  # fmt: skip
    progress.plan = initial_plan(run, progress, planned)
    segment_fits = None
    while not progress.done:
        if before_final(run, progress):  # the horizon cut, and the noisy refit in place of longer segments
            run.checkpoint(progress)
        stage = stage_for(run, progress)
        state = stage.init(progress)
        while not stage.done(state):
            state = stage.step(state)
            if stage.checkpoints:
                run.checkpoint(progress)
        fits = stage.result(state)
        segment_fits = fits if fits is not None else segment_fits
        progress.next_stage()
        if progress.done:
            after_last(run, progress)  # the noisy refit after the plan
        run.checkpoint(progress)
    results = collect_results(run, progress, start_values, identify, segment_fits)
    return [dataclasses.replace(r, search=search) for r in results] if search else results
