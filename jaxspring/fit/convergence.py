"""When a fit's stage has converged (the stop rules of `FitSettings`)."""

from __future__ import annotations

import numpy as np

from .results import FitProgress
from .settings import FitSettings


def converged(progress: FitProgress, settings: FitSettings, final_stage: bool, opt_state, floor: float) -> bool:
    """Whether every member has converged in the current stage (see FitSettings). An ensemble
    stage says so itself, or stops when it fits its target to round-off (`floor`, the loss of
    positions that differ by round-off): without noise its cloud would otherwise shrink
    towards standard errors of zero for all its iterations. Gradient stages stop on their
    steps and loss alone, which reach further than that floor (in float32 by far)."""
    if isinstance(opt_state, dict) and "done" in opt_state:  # an ensemble stage
        current = progress.loss and progress.stage_of_iteration[-1] == progress.stage
        return bool(np.all(np.asarray(opt_state["done"]) > 0) or (current and np.all(progress.loss[-1] <= floor)))
    if progress.last_step is not None:
        limit = settings.step_tolerance if final_stage else settings.warmup_step_tolerance
        if np.all(progress.last_step <= limit):
            return True
    in_stage = [loss for loss, s in zip(progress.loss, progress.stage_of_iteration) if s == progress.stage]
    if len(in_stage) < 2:
        return False
    first, now = np.asarray(in_stage[0]), np.asarray(in_stage[-1])
    if np.all(now <= settings.tolerance**2 * first):
        return True
    if len(in_stage) < 6 or settings.optimizer != "lbfgs":  # Adam's loss is not monotone
        return False
    before = np.asarray(in_stage[-6])
    return bool(np.all((before - now) <= settings.tolerance * np.abs(before)))
