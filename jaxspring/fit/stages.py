"""The stages of a fit as objects with one protocol (optax's init/update shape).

Every stage runs the same way (`fit.loop.fit_batch`):

    state = stage.init(progress)    # compile its iteration, restore a resumed stage's optimizer
    while not stage.done(state):
        state = stage.step(state)   # one iteration: `progress` gains a loss and values
    stage.result(state)             # `progress.theta`: where the stage ends

`progress` (a `FitProgress`) is what every stage advances and what a checkpoint saves; a
stage's own state (`IterationState`) holds only what is rebuilt from it on resume. The stages:

- `OptimiserStage`: iterations of an optimiser on the stage's loss ("direct", "shooting",
  "ensemble" stages): L-BFGS or Adam on the misfit, Levenberg-Marquardt on its residuals
  (`least_squares.lm_step_function`), or the ensemble's smoothed Gauss-Newton (`ensemble`).
  It ends on the best point it has seen; a shooting stage on exact data ends with
  Levenberg-Marquardt steps (`least_squares.finish_shooting_stage`).
- `Retreat` wraps an optimiser stage: where it stops early, it goes on from softer values
  (`gradient.retreat`), at most `gradient.RETREATS` times.
- `SegmentStates`: Levenberg-Marquardt with the segments' start states ("free_shooting",
  "position_shooting"), one step per member (`position_shooting.free_shooting_stage`).

`stage_for` picks the object for a `Stage` of the plan (`fit.plan`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Protocol

import jax
import jax.numpy as jnp
import numpy as np

from ..resources import check_compiled
from ..sim.scene import Scene
from ..sim.sharding import shard_batch
from .ensemble import ensemble_step_function
from .gradient import RETREATS, converged, keep_best_of_stage, retreat, step_function
from .horizon import round_off_loss
from .least_squares import finish_shooting_stage, least_squares_residual, lm_step_function, stage_optimizer
from .objective import loss_function
from .position_shooting import free_shooting_stage
from .progress import FitProgress
from .recordings import RecordingTarget
from .settings import SEGMENT_STATES, FitSettings, Stage


@dataclasses.dataclass(frozen=True)
class FitRun:
    """What every stage of one `fit_batch` call shares: the model, the targets (one, or one per
    member) and their arrays (`data`), the fitted names, the settings, the batch and where its
    members live, and the checkpoint callback."""

    scene: Scene
    observations: list
    names: tuple
    settings: FitSettings
    data: dict
    batched_data: bool
    members: int
    members_sharded: bool
    max_memory: int | None
    on_iteration: Callable | None
    start_clock: float

    @property
    def reference(self):
        """The first target: its shape and kind stand for all."""
        return self.observations[0]

    def placed(self, theta: dict) -> dict:
        """`theta` on the devices the members are split across (as it is when they are not)."""
        return shard_batch(theta) if self.members_sharded else theta

    def checkpoint(self, progress: FitProgress) -> None:
        """Count the time so far and hand `progress` to the caller's `on_iteration`."""
        progress.wall_s = time.perf_counter() - self.start_clock
        if self.on_iteration:
            self.on_iteration(progress, progress.plan)


class StageRunner(Protocol):
    """The protocol of a fit's stages (module docstring). `checkpoints`: whether a checkpoint
    after each `step` resumes exactly (a step that runs a whole solve does not)."""

    checkpoints: bool

    def init(self, progress: FitProgress): ...

    def step(self, state): ...

    def done(self, state) -> bool: ...

    def result(self, state): ...


@dataclasses.dataclass
class IterationState:
    """An optimiser stage's state: the running `progress`, the optimizer's state, and the last
    iteration's largest move per member (`previous`)."""

    progress: FitProgress
    opt_state: object
    previous: np.ndarray | None


class OptimiserStage:
    """Iterations of an optimiser on a stage's loss (module docstring), batched over the members."""

    checkpoints = True

    def __init__(self, run: FitRun, stage: Stage, final: bool):
        self.run, self.stage, self.final = run, stage, final

    def init(self, progress: FitProgress) -> IterationState:
        run, stage, settings = self.run, self.stage, self.run.settings
        self.value = None  # the stage's loss per member (None for the ensemble: no gradients)
        if stage.kind == "ensemble":
            step, init_opt = ensemble_step_function(
                run.scene, run.reference, run.names, stage, settings, run.batched_data, progress.theta
            )
        else:
            loss = loss_function(run.scene, run.reference, run.names, stage)
            step, init_opt, self.value = step_function(loss, settings, run.batched_data)
            residual = least_squares_residual(run.scene, run.reference, run.names, stage, settings, progress.theta)
            if residual is not None:  # Levenberg-Marquardt on the stage's residuals
                step, init_opt = lm_step_function(residual, run.batched_data)
            settings = dataclasses.replace(settings, optimizer=stage_optimizer(settings, residual))
        self.settings, self.init_opt = settings, init_opt
        opt_state = init_opt(progress.theta)
        if progress.optimizer_leaves is not None:  # resumed inside the stage
            structure = jax.tree_util.tree_structure(opt_state)
            opt_state = jax.tree_util.tree_unflatten(structure, [jnp.asarray(a) for a in progress.optimizer_leaves])
        self.compiled = check_compiled(
            step,
            (progress.theta, opt_state, run.data),
            f"an iteration of the {stage.kind} stage ({run.members} start(s), {stage.frames} frames)",
            "fit",
            "fit fewer frames, recordings or starts, or fit in segments (strategy shooting)",
            run.max_memory,
        )
        self.floor = round_off_loss(run.scene, run.reference)
        # resumed: the checkpoint's last step, at most as small as the last one
        return IterationState(progress, opt_state, previous=progress.last_step)

    def step(self, state: IterationState) -> IterationState:
        progress, names = state.progress, self.run.names
        values = {n: np.asarray(jnp.exp(progress.theta[n])) for n in names}
        theta, state.opt_state, value = self.compiled(progress.theta, state.opt_state, self.run.data)
        moves = [
            np.abs(np.asarray(theta[n] - progress.theta[n])).reshape(self.run.members, -1).max(axis=1) for n in names
        ]
        moved = np.max(np.stack(moves), axis=0)
        # over two iterations: one line search that stalls (in float32 L-BFGS's does, with
        # a badly scaled curvature) is followed by a long step, not by convergence
        progress.last_step = None if state.previous is None else np.maximum(moved, state.previous)
        state.previous = moved
        progress.theta = theta
        progress.loss.append(np.asarray(value))
        for n in names:
            progress.values[n].append(values[n])
        progress.stage_of_iteration.append(progress.stage)
        progress.iteration += 1
        progress.optimizer_leaves = [np.asarray(a) for a in jax.tree_util.tree_leaves(state.opt_state)]
        return state

    def converged(self, state: IterationState) -> bool:
        """The stop rules of `FitSettings` (`gradient.converged`)."""
        return converged(state.progress, self.settings, self.final, state.opt_state, self.floor)

    def done(self, state: IterationState) -> bool:
        return state.progress.iteration >= self.settings.iterations or self.converged(state)

    def result(self, state: IterationState) -> None:
        progress, run = state.progress, self.run
        went_back, loss = keep_best_of_stage(progress, run.names, self.compiled, state.opt_state, run.data)
        if went_back:
            progress.theta = run.placed(progress.theta)
        if self.stage.kind == "shooting" and not isinstance(run.reference, RecordingTarget):
            finish_shooting_stage(
                run.scene,
                run.observations,
                run.names,
                self.stage.frames,
                run.settings,
                progress,
                loss,
                run.members_sharded,
            )


class Retreat:
    """An optimiser stage (L-BFGS or Levenberg-Marquardt on a loss) that, where its stop rules
    end it before its iteration budget, goes on from softer values when they are lower
    (`gradient.retreat`: off the stability wall), with a fresh optimizer, at most
    `RETREATS` times per stage (a resumed stage counts the retreats it made before)."""

    checkpoints = True

    def __init__(self, inner: OptimiserStage):
        self.inner = inner

    def init(self, progress: FitProgress) -> IterationState:
        state = self.inner.init(progress)
        began = len(progress.loss) - progress.iteration
        retreating = self.inner.value is not None and self.inner.settings.optimizer in ("lbfgs", "lm")
        self.left = RETREATS - sum(1 for i, _ in progress.retreats if i >= began) if retreating else 0
        return state

    def step(self, state: IterationState) -> IterationState:
        return self.inner.step(state)

    def done(self, state: IterationState) -> bool:
        """Where the stop rules would end the stage early, the retreat is tried first: if it
        moved a member, the stage goes on from there with a fresh optimizer."""
        progress, inner = state.progress, self.inner
        if progress.iteration >= inner.settings.iterations:
            return True
        if not inner.converged(state):
            return False
        if self.left <= 0:
            return True
        moved = retreat(progress, inner.run.names, inner.value, inner.run.data)
        if not moved.any():
            return True
        self.left -= 1
        progress.retreats.append((len(progress.loss), moved))
        state.opt_state, progress.last_step, state.previous = inner.init_opt(progress.theta), None, None
        return False

    def result(self, state: IterationState) -> None:
        return self.inner.result(state)


@dataclasses.dataclass
class SegmentState:
    progress: FitProgress
    fits: list | None = None


class SegmentStates:
    """Levenberg-Marquardt with the segments' start states ("free_shooting",
    "position_shooting"): one step fits every member (`free_shooting_stage`); `result`
    returns each member's `SegmentFit` (the report's standard errors come from them)."""

    checkpoints = False

    def __init__(self, run: FitRun, stage: Stage):
        self.run, self.stage = run, stage

    def init(self, progress: FitProgress) -> SegmentState:
        return SegmentState(progress)

    def step(self, state: SegmentState) -> SegmentState:
        run = self.run
        state.fits = free_shooting_stage(
            run.scene, run.observations, run.names, self.stage, run.settings, state.progress
        )
        state.progress.theta = run.placed(state.progress.theta)
        return state

    def done(self, state: SegmentState) -> bool:
        return state.fits is not None

    def result(self, state: SegmentState) -> list:
        return state.fits


def stage_for(run: FitRun, progress: FitProgress) -> StageRunner:
    """The object that runs the plan's current stage (`progress.plan[progress.stage]`)."""
    stage = progress.plan[progress.stage]
    if stage.kind in SEGMENT_STATES:
        return SegmentStates(run, stage)
    return Retreat(OptimiserStage(run, stage, final=progress.stage == len(progress.plan) - 1))
