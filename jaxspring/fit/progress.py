"""Where a running fit stands: everything needed to continue it exactly (saved in fit files)."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class FitProgress:
    """Everything needed to continue a fit exactly where it stopped (saved in fit files).

    Attributes:
        stage: index of the current stage.
        iteration: iterations done in the current stage.
        theta: log parameter values, name -> (B, ...); with a fitted start state also
            "start" -> (B, R, N, 6), with fitted driven paths "driven" -> (B, R, F, D, 3)
            (see `recording_loss.start_unknowns`).
        optimizer_leaves: the optimizer state's arrays (its structure is rebuilt from the settings).
        loss: loss before each completed iteration, list of (B,) arrays.
        values: parameter values before each completed iteration, name -> list of (B, ...) arrays.
        stage_of_iteration: stage index of each completed iteration.
        last_step: largest log-parameter change of the last two iterations, per member (B,).
        done: whether the fit finished.
        wall_s: time spent so far [s].
        horizon: frames the final stage's misfit stays smooth over, once measured
            (`fit.horizon`; None before, or when the plan does not ask).
        refit_frames: segment frames of a "position_shooting" stage added after the plan's last
            one, whose answer left more misfit than the recorded positions' noise, or in place
            of a last one of longer segments from them (`fit.plan.refit_from`,
            `refit_stages`); None when none was added.
        retreats: (iteration, members moved (B,) bool) for each time a stage that stopped early
            went on from softer values (`fit.gradient.retreat`); the iteration indexes `loss`.
        plan: the fit's stages (`fit.plan`), as its transitions left them; saved in fit files,
            so a resumed fit runs the same stages.
    """

    stage: int
    iteration: int
    theta: dict
    optimizer_leaves: list | None
    loss: list
    values: dict
    stage_of_iteration: list
    last_step: np.ndarray | None = None
    done: bool = False
    wall_s: float = 0.0
    horizon: int | None = None
    refit_frames: int | None = None
    retreats: list = dataclasses.field(default_factory=list)
    plan: list | None = None

    def next_stage(self) -> None:
        """Leave the current stage: the next one starts with a fresh optimizer."""
        self.stage += 1
        self.iteration = 0
        self.optimizer_leaves = None
        self.last_step = None
        self.done = self.stage >= len(self.plan)
