"""The fit loop: optimiser stages over a batch of starts and targets, convergence, results."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..resources import check_compiled
from ..sim.scene import Scene
from ..sim.sharding import shard_batch
from .ensemble import ensemble_step_function
from .gradient import RETREATS, best_of_stages, keep_best_of_stage, retreat, step_function
from .gradient import converged as _converged
from .horizon import describe_segments, describe_smoothness, horizon_stage, measure_horizon, round_off_loss
from .identifiability import gauss_newton_polish, identifiability_report, start_polish
from .least_squares import finish_shooting_stage, least_squares_residual, lm_step_function, stage_optimizer
from .noisy_states import refit_from, refit_stages, why_refit
from .objective import check_names, loss_function, target_data
from .observations import Observations
from .position_shooting import describe, free_shooting_stage, segment_fitter
from .progress import FitProgress
from .recording_loss import NUISANCE, estimated_inputs, start_unknowns, with_fitted_start
from .recordings import RecordingTarget, warn_of_noisy_driven_paths
from .results import FitResult
from .search import needs_search, search_start
from .settings import SEGMENT_STATES, FitSettings, Stage, needs_horizon, plan_stages


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
    `progress` continues an interrupted fit; `on_iteration(progress, stages)` is called
    after every iteration (the CLI checkpoints from it). With several devices in one process and a
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
    stages = plan_stages(reference, settings, scene, values=sum(math.prod(shapes[n]) for n in names))
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
    start_clock = time.perf_counter() - progress.wall_s
    run = _Run(
        scene,
        observations,
        reference,
        names,
        stages,
        settings,
        data,
        batched_data,
        members,
        members_sharded,
        max_memory,
        on_iteration,
        start_clock,
    )
    if progress.horizon is not None and needs_horizon(stages, reference):  # resumed, or a finished fit read back
        stages[-1] = horizon_stage(scene, observations, names, settings, stages[-1], progress.horizon)
    if progress.refit_frames is not None:
        refit_stages(stages, progress.refit_frames)
    segment_fits = None
    while not progress.done:
        if progress.stage == len(stages) - 1 and needs_horizon(stages, reference):
            if progress.horizon is None:  # measured once, at the shooting answer; a resumed fit reads it
                progress.horizon = measure_horizon(scene, observations, names, settings.horizon_spread, progress.theta)
            stages[-1] = horizon_stage(scene, observations, names, settings, stages[-1], progress.horizon)
            start = refit_from(scene, observations, names, settings, stages, progress, data, before_final=True)
            if start is not None:  # segments from noisy recorded states: their starts are fitted instead
                progress.theta, progress.refit_frames = start, stages[0].frames
                refit_stages(stages, progress.refit_frames)
                if on_iteration:  # a checkpoint keeps the decision
                    on_iteration(progress, stages)
        stage = stages[progress.stage]
        if stage.kind in SEGMENT_STATES:  # Levenberg-Marquardt with the segments' states, per member
            segment_fits = free_shooting_stage(scene, observations, names, stage, settings, progress)
            progress.theta = shard_batch(progress.theta) if members_sharded else progress.theta
        else:
            _optimiser_stage(run, stage, progress)
        progress.stage += 1
        progress.iteration = 0
        progress.optimizer_leaves = None
        progress.last_step = None
        progress.done = progress.stage >= len(stages)
        if progress.done and progress.refit_frames is None:
            start = refit_from(scene, observations, names, settings, stages, progress, data)
            if start is not None:  # the recorded states are noisy: fit their positions too
                progress.theta, progress.refit_frames, progress.done = start, stages[0].frames, False
                refit_stages(stages, progress.refit_frames)
        progress.wall_s = time.perf_counter() - start_clock
        if on_iteration:
            on_iteration(progress, stages)
    results = _results(
        scene, observations, names, start_values, settings, stages, progress, data, identify, segment_fits
    )
    return [dataclasses.replace(r, search=search) for r in results] if search else results


@dataclasses.dataclass(frozen=True)
class _Run:
    """What every stage of one `fit_batch` call shares."""

    scene: Scene
    observations: list
    reference: Observations
    names: tuple
    stages: list
    settings: FitSettings
    data: dict
    batched_data: bool
    members: int
    members_sharded: bool
    max_memory: int | None
    on_iteration: Callable | None
    start_clock: float


def _optimiser_stage(run: _Run, stage: Stage, progress: FitProgress):
    """Run one optimiser stage (direct, shooting from recorded states, ensemble) to convergence."""
    scene, reference, names, stages, settings, data = (
        run.scene,
        run.reference,
        run.names,
        run.stages,
        run.settings,
        run.data,
    )
    batched_data, members, members_sharded = run.batched_data, run.members, run.members_sharded
    max_memory, on_iteration, start_clock = run.max_memory, run.on_iteration, run.start_clock
    if stage.kind == "ensemble":
        step, init_opt = ensemble_step_function(scene, reference, names, stage, settings, batched_data, progress.theta)
        loss_of = None
    else:
        step, init_opt, loss_of = step_function(loss_function(scene, reference, names, stage), settings, batched_data)
        residual = least_squares_residual(scene, reference, names, stage, settings, progress.theta)
        if residual is not None:  # Levenberg-Marquardt on the stage's residuals
            step, init_opt = lm_step_function(residual, batched_data)
        settings = dataclasses.replace(settings, optimizer=stage_optimizer(settings, residual))
    opt_state = init_opt(progress.theta)
    if progress.optimizer_leaves is not None:
        structure = jax.tree_util.tree_structure(opt_state)
        opt_state = jax.tree_util.tree_unflatten(structure, [jnp.asarray(a) for a in progress.optimizer_leaves])
    step = check_compiled(
        step,
        (progress.theta, opt_state, data),
        f"an iteration of the {stage.kind} stage ({members} start(s), {stage.frames} frames)",
        "fit",
        "fit fewer frames, recordings or starts, or fit in segments (strategy shooting)",
        max_memory,
    )
    final_stage = progress.stage == len(stages) - 1
    floor = round_off_loss(scene, reference)
    previous = progress.last_step  # resumed: the checkpoint's, at most as small as the last step
    # the stage's retreats so far count (a resumed stage goes on as an uninterrupted one)
    stage_began = len(progress.loss) - progress.iteration
    used = sum(1 for i, _ in progress.retreats if i >= stage_began)
    retreats = RETREATS - used if loss_of is not None and settings.optimizer in ("lbfgs", "lm") else 0
    while progress.iteration < settings.iterations:
        if _converged(progress, settings, final_stage, opt_state, floor):
            # stopped early: on the stability wall, a softer point is lower (fit.gradient.retreat)
            moved = retreat(progress, names, loss_of, data) if retreats else None
            if moved is None or not moved.any():
                break
            retreats -= 1
            progress.retreats.append((len(progress.loss), moved))
            opt_state, progress.last_step, previous = init_opt(progress.theta), None, None
        values = {n: np.asarray(jnp.exp(progress.theta[n])) for n in names}
        theta, opt_state, value = step(progress.theta, opt_state, data)
        moved = np.max(
            np.stack(
                [np.abs(np.asarray(theta[n] - progress.theta[n])).reshape(members, -1).max(axis=1) for n in names]
            ),
            axis=0,
        )
        # over two iterations: one line search that stalls (in float32 L-BFGS's does, with
        # a badly scaled curvature) is followed by a long step, not by convergence
        progress.last_step = None if previous is None else np.maximum(moved, previous)
        previous = moved
        progress.theta = theta
        progress.loss.append(np.asarray(value))
        for n in names:
            progress.values[n].append(values[n])
        progress.stage_of_iteration.append(progress.stage)
        progress.iteration += 1
        progress.optimizer_leaves = [np.asarray(a) for a in jax.tree_util.tree_leaves(opt_state)]
        progress.wall_s = time.perf_counter() - start_clock
        if on_iteration:
            on_iteration(progress, stages)
    went_back, loss = keep_best_of_stage(progress, names, step, opt_state, data)
    if went_back:
        progress.theta = shard_batch(progress.theta) if members_sharded else progress.theta
    if stage.kind == "shooting" and not isinstance(reference, RecordingTarget):
        finish_shooting_stage(
            run.scene, run.observations, names, stage.frames, run.settings, progress, loss, members_sharded
        )


def _results(scene, observations, names, start_values, settings, stages, progress, data, identify, segment_fits):
    batched_data = len(observations) > 1
    if stages[-1].kind in SEGMENT_STATES:  # downhill on each continuity weight's objective, ending on the last
        if segment_fits is None:  # resumed after the stage: settle the states at the answer again
            fit_of = segment_fitter(stages[-1].kind)
            segment_fits = [
                fit_of(
                    scene,
                    observations[m if batched_data else 0],
                    names,
                    {n: np.exp(np.asarray(progress.theta[n][m], dtype=float)) for n in names},
                    stages[-1].frames,
                    settings.iterations,
                    settings.step_tolerance,
                )
                for m in range(len(start_values))
            ]
            progress.theta = {n: jnp.stack([jnp.log(jnp.asarray(f.values[n])) for f in segment_fits]) for n in names}
        final_loss = np.array([f.loss for f in segment_fits])
    else:
        loss = loss_function(scene, observations[0], names, stages[-1])
        _, _, value = step_function(loss, settings, batched_data)
        progress.theta, final_loss = best_of_stages(progress, names, value, data)
    results = []
    total = observations[0].frame_count - 1
    segment = stages[-1].frames if stages[-1].kind == "shooting" else None  # the final misfit over segments
    polish_stage = Stage("gauss_newton", segment or total)
    horizon_objective, horizon_words = {}, ""
    if progress.horizon is not None:  # the final stage was fitted to the horizon measured after the others
        horizon_words = describe_smoothness(progress.horizon, total, settings.horizon_spread)
        horizon_objective = dict(
            segment=segment,
            objective=describe_segments(segment, total, progress.horizon, settings.horizon_spread),
        )
    for member, start in enumerate(start_values):
        obs = observations[member if batched_data else 0]
        final = {n: np.asarray(jnp.exp(progress.theta[n][member])) for n in names}
        history = [np.asarray(loss)[member] for loss in progress.loss]
        value_history = {n: [v[member] for v in progress.values[n]] for n in names}
        stage_of_iteration = list(progress.stage_of_iteration)
        polish_start = time.perf_counter()
        estimated = None
        if "start" in progress.theta:  # fitted start states: always polished with them (least squares)
            nuisance = {k: np.asarray(progress.theta[k][member]) for k in NUISANCE if k in progress.theta}
            steps = start_polish(scene, obs, names, final, nuisance, settings) if obs.loss == "mse" else []
            obs = with_fitted_start(obs, steps.nuisance if steps else nuisance)  # reported with them held
            estimated = estimated_inputs(obs, "driven" in nuisance)
        else:
            whole = settings.polish and stages[-1].kind not in SEGMENT_STATES  # never past the segments
            steps = gauss_newton_polish(scene, obs, names, final, settings, segment=segment) if whole else []
        for loss_before, values_before in steps:
            history.append(loss_before)
            for n in names:
                value_history[n].append(values_before[n])
            stage_of_iteration.append(len(stages))
        if steps:
            final = steps.final
            final_loss_member = steps.final_loss
        else:
            final_loss_member = final_loss[member]
        reduced = getattr(steps, "reduced", None)  # start states estimated too: their uncertainty counts
        shooting = {"normal": reduced, "nuisance": steps.unknowns if reduced is not None else 0, **horizon_objective}
        if segment_fits is not None and stages[-1].kind in SEGMENT_STATES:  # standard errors of that objective
            fit = segment_fits[member]
            dof = max(fit.count + fit.link_rows - len(fit.reduced) - fit.unknowns, 1)
            shooting = dict(
                normal=fit.reduced,
                nuisance=fit.unknowns,
                noise_variance=fit.loss * fit.count / dof,
                objective=describe(fit) + why_refit(stages, progress, horizon_words),
            )
            estimated = {
                "segment_x": np.asarray(fit.starts.x),
                "segment_v": np.asarray(fit.starts.v),
                "segment_frame": np.asarray(fit.first_frames),
            }
        ident = identifiability_report(scene, obs, names, final, **shooting) if identify else None
        if ident and isinstance(obs, RecordingTarget) and not (estimated and "driven" in estimated):
            ident = warn_of_noisy_driven_paths(obs, ident)
        results.append(
            FitResult(
                names=names,
                initial={n: np.asarray(start[n]) for n in names},
                final=final,
                loss_history=np.array(history + [final_loss_member]),
                value_history={n: np.array(value_history[n] + [final[n]]) for n in names},
                stages=tuple(stages) + ((polish_stage,) if steps else ()),
                stage_of_iteration=np.asarray(stage_of_iteration, dtype=int),
                iterations=len(history),
                wall_s=progress.wall_s + time.perf_counter() - polish_start,
                identifiability=ident,
                truth={n: obs.truth[n] for n in names if n in obs.truth} if obs.truth else None,
                truth_label=getattr(obs, "truth_label", "true"),
                estimated=estimated,
                retreats=tuple(i for i, moved in progress.retreats if moved[member]),
            )
        )
    return results
