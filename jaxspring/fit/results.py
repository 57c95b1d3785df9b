"""What a fit returns: the result of one member, with its identifiability report."""

from __future__ import annotations

import dataclasses

import numpy as np

from .identifiability import Identifiability


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
