"""What a fit returns: the result of one member, with its identifiability report, and how a
finished fit's progress becomes those results (`collect_results`)."""

from __future__ import annotations

import dataclasses
import time

import jax.numpy as jnp
import numpy as np

from .gradient import best_of_stages, step_function
from .horizon import describe_segments, describe_smoothness
from .identifiability import Identifiability, gauss_newton_polish, identifiability_report, start_polish
from .objective import loss_function
from .plan import why_refit
from .position_shooting import describe, member_segment_fits
from .progress import FitProgress
from .recording_loss import NUISANCE, estimated_inputs, with_fitted_start
from .recordings import RecordingTarget, warn_of_noisy_driven_paths
from .settings import SEGMENT_STATES, Stage
from .stages import FitRun


@dataclasses.dataclass(frozen=True)
class FitResult:
    """The outcome of a fit (one member; `fit_batch` returns a list of these).

    Attributes:
        names: fitted parameter names.
        initial, final: name -> value at the start and at the end.
        loss_history: loss [m^2] before each iteration, then the final loss, shape (iterations + 1,).
        value_history: name -> value before each iteration, then the final value.
        stages: the stages run; stage_of_iteration says which stage each iteration belongs to.
        iterations: iterations run in all.
        wall_s: wall time [s].
        identifiability: Gauss-Newton standard errors and correlations (None if skipped).
        truth: true values when known (synthetic targets), or a target file's own values.
        truth_label: "true", or "file" when `truth` holds a target file's values.
        estimated: what a recording fit estimated besides the parameters (None otherwise):
            "x0", "v0" the recordings' start states (R, N, 3) with `fit_start`, and
            "driven" the driven particles' paths (R, F, D, 3) at the frames from the
            start frame on with `fit_driven` [m, m/s]; after multiple shooting with free
            states, "segment_x", "segment_v": the segments' fitted start states (S, N, 3),
            "segment_frame": each segment's first frame (S,) (segments that touch the ground
            are left out).
        search: the start search's `fit.search.SearchReport` on recordings (None without one).
        retreats: iterations (indices into `loss_history`) from which a stage that stopped early,
            stalled on the time step's stability wall, went on from softer values (`fit.retreat`).
    """

    names: tuple
    initial: dict
    final: dict
    loss_history: np.ndarray
    value_history: dict
    stages: tuple
    stage_of_iteration: np.ndarray
    iterations: int
    wall_s: float
    identifiability: Identifiability | None
    truth: dict | None = None
    truth_label: str = "true"
    estimated: dict | None = None
    search: object | None = None
    retreats: tuple = ()

    @property
    def final_loss(self) -> float:
        return float(self.loss_history[-1])

    def relative_errors(self) -> dict:
        """name -> |final - true| / |true| (max over items for per-item parameters), when the truth is known."""
        if not self.truth:
            return {}
        return {
            n: float(np.max(np.abs(np.asarray(self.final[n]) - self.truth[n]) / np.abs(self.truth[n])))
            for n in self.names
            if n in self.truth
        }

    def moved(self) -> dict:
        """name -> fitted / initial value (the mean ratio for per-item parameters)."""
        return {
            n: float(np.mean(np.asarray(self.final[n], dtype=float) / np.asarray(self.initial[n], dtype=float)))
            for n in self.names
        }

    def table(self) -> str:
        """A plain-text table: fitted value, true value, relative error, standard error."""
        ident = self.identifiability
        width = max([7] + [len(n) + 1 for n in self.names])
        label = "file values" if self.truth_label == "file" else "true"
        diff = "rel. diff." if self.truth_label == "file" else "rel. error"
        rows = [f"{'param':<{width}}{'initial':>12}{'fitted':>14}{label:>12}{diff:>12}{'std. error':>12}"]
        errors = self.relative_errors()
        for n in self.names:
            value = np.asarray(self.final[n])
            true = "" if not self.truth or n not in self.truth else _short(self.truth[n])
            rel = f"{errors[n]:.2e}" if n in errors else ""
            se = _short(ident.standard_error[n]) if ident else ""
            rows.append(f"{n:<{width}}{_short(self.initial[n]):>12}{_short(value):>14}{true:>12}{rel:>12}{se:>12}")
        rows.append(f"final loss {self.final_loss:.4g} m^2 after {self.iterations} iterations in {self.wall_s:.2f} s")
        if self.search is not None:
            rows.append(self.search.summary())
        if self.retreats:
            rows.append(
                f"stalled {len(self.retreats)} time(s) before its iteration budget and went on from softer values "
                f"(stiffness, damping and drag lower) at iteration(s) {', '.join(map(str, self.retreats))}"
            )
        moved = self.moved()
        stalled = [n for n, r in moved.items() if abs(r - 1) < 0.01]
        rows.append("moved from the initial values: " + ", ".join(f"{n} x{r:.3g}" for n, r in moved.items()))
        if stalled:
            rows.append(
                f"note: {', '.join(stalled)} moved less than 1% from the initial values (fine if they were right;"
                " a fit that stalls at its start has not measured them: try other initial values)"
            )
        if ident:
            rows.append(f"minimised: {ident.objective}")
            rows += [f"warning: {w}" for w in ident.warnings]
        return "\n".join(rows)


def _short(value) -> str:
    value = np.asarray(value)
    if value.ndim == 0:
        return f"{float(value):.6g}"
    return f"mean {float(value.mean()):.4g}"


def collect_results(run: FitRun, progress: FitProgress, start_values: list, identify: bool, segment_fits) -> list:
    """A `FitResult` per member of a finished fit: the best point of its plan on the final
    objective (`gradient.best_of_stages`; segment-state stages: their fits, settled again
    when resumed after them), the polish (`FitSettings.polish`, fitted start states always),
    and the identifiability report of the objective the final stage minimised."""
    scene, observations, names, settings, data = run.scene, run.observations, run.names, run.settings, run.data
    stages, batched_data = progress.plan, run.batched_data
    if stages[-1].kind in SEGMENT_STATES:  # downhill on each continuity weight's objective, ending on the last
        if segment_fits is None:  # resumed after the stage: settle the states at the answer again
            segment_fits = member_segment_fits(scene, observations, names, stages[-1], settings, progress.theta)
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
