"""Prediction: simulate recordings with fitted values, their error, and prediction bands."""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import BlowUpError, InputError
from ..io.recording import matched_by_name
from ..resources import check_compiled, check_memory
from .identifiability import unique_names
from .recording_loss import carriers, markers_simulated, target_data
from .recordings import RecordingTarget, recording_target

MIN_BAND_DRAWS = 16
"""Fewest parameter sets a 95% band is drawn from (its 2.5% and 97.5% percentiles need at
least this many to mean anything); fewer stable ones than this gives a warning."""


@dataclasses.dataclass(frozen=True)
class Prediction:
    """One recording predicted from its start frame.

    Errors are taken over the frames after `start` and every marker seen there (the driven
    ones too). Two names for two numbers: `mean_coordinate_error` is the mean |error| over the
    x, y and z coordinates (the number motion-capture papers quote), `mean_distance` the mean
    Euclidean distance between predicted and seen markers (about 1.6x larger for errors in
    random directions).

    Attributes:
        name: the recording's name.
        t: frame times [s], (F,), the recording's.
        x: predicted marker positions [m], (F, M, 3); frames before `start` copied from the recording.
        recorded: the recording's marker positions (NaN where not seen).
        start: the first simulated frame.
        mean_coordinate_error: mean |predicted - seen| per coordinate [m].
        mean_distance: mean distance |predicted - seen| [m].
        rms_error: root-mean-square of that distance [m].
        marker_coordinate_error: mean |error| per coordinate of each marker [m], (M,) (NaN for a
            marker never seen after `start`); marker_seen: its seen frames after `start`, (M,).
        low, high: the 95% prediction band per marker, frame and axis (None without bands).
        coverage: the fraction of seen marker coordinates after `start` inside the band.
        frozen_coordinate_error, frozen_distance: the baseline: the same errors when the free
            markers stay where they were at `start` and the driven ones move as recorded.
        band_draws: the parameter sets drawn for the band; band_unstable: how many of them blew
            up (past the time step's stability limit) and were left out of it.
    """

    name: str
    t: np.ndarray
    x: np.ndarray
    recorded: np.ndarray
    start: int
    mean_coordinate_error: float
    mean_distance: float
    rms_error: float
    marker_coordinate_error: np.ndarray
    marker_seen: np.ndarray
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    coverage: float | None = None
    frozen_coordinate_error: float | None = None
    frozen_distance: float | None = None
    marker_names: tuple = ()
    band_draws: int = 0
    band_unstable: int = 0

    @property
    def coordinate_errors(self) -> np.ndarray:
        """|predicted - seen| [m] after `start`, (F - start - 1, M, 3), NaN where not seen."""
        return np.abs(self.x[self.start + 1 :] - self.recorded[self.start + 1 :])


@dataclasses.dataclass(frozen=True)
class ErrorSummary:
    """Errors pooled over predictions: every seen marker coordinate after each start counts once.

    Attributes:
        mean_coordinate_error, mean_distance, rms_error: as in `Prediction` [m], pooled.
        frozen_coordinate_error, frozen_distance: the frozen-at-start baseline, pooled [m].
        marker_coordinate_error: per marker [m], (M,).
        over_time: mean |error| per coordinate at each frame after the start over every
            recording long enough [m], (F,), with `time` [s] from the start frame.
        coverage: pooled 95% band coverage (None without bands).
    """

    mean_coordinate_error: float
    mean_distance: float
    rms_error: float
    frozen_coordinate_error: float
    frozen_distance: float
    marker_coordinate_error: np.ndarray
    over_time: np.ndarray
    time: np.ndarray
    coverage: float | None


def summarise(predictions) -> ErrorSummary:
    """Pool the errors of `predictions` (of one marker set): see `ErrorSummary`.

    Example:
        >>> summary = js.fitting.summarise(js.predict(scene, values, recordings, driven=[0, 1, 10, 11]))
        >>> summary.mean_coordinate_error  # [m]
    """
    predictions = list(predictions)
    if not predictions:
        raise ValueError("no predictions to summarise")
    errors = [p.coordinate_errors for p in predictions]
    flat = np.concatenate([e[np.isfinite(e)] for e in errors])
    distances = [np.sqrt(np.sum(e**2, axis=-1)) for e in errors]
    flat_d = np.concatenate([d[np.isfinite(d)] for d in distances])
    count = np.sum([p.marker_seen for p in predictions], axis=0)
    longest = max(e.shape[0] for e in errors)
    totals, counts = np.zeros(longest), np.zeros(longest)
    for e in errors:
        finite = np.isfinite(e)
        totals[: e.shape[0]] += np.where(finite, e, 0.0).sum(axis=(1, 2))
        counts[: e.shape[0]] += finite.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        per_marker = np.nansum([p.marker_coordinate_error * p.marker_seen for p in predictions], axis=0) / count
        over_time = totals / counts
    seen = [np.isfinite(e).all(axis=-1).sum() for e in errors]
    frozen_c = np.sum([p.frozen_coordinate_error * n for p, n in zip(predictions, seen)]) / max(sum(seen), 1)
    frozen_d = np.sum([p.frozen_distance * n for p, n in zip(predictions, seen)]) / max(sum(seen), 1)
    first = predictions[0]
    interval = float(np.median(np.diff(first.t))) if first.t.size > 1 else 1.0
    time = interval * np.arange(1, longest + 1)
    covered = [p.coverage for p in predictions if p.coverage is not None]
    coverage = (
        float(np.sum([c * n for c, n in zip(covered, seen)]) / max(sum(seen), 1))
        if len(covered) == len(predictions)
        else None
    )
    return ErrorSummary(
        mean_coordinate_error=float(flat.mean()) if flat.size else float("nan"),
        mean_distance=float(flat_d.mean()) if flat_d.size else float("nan"),
        rms_error=float(np.sqrt(np.mean(flat_d**2))) if flat_d.size else float("nan"),
        frozen_coordinate_error=float(frozen_c),
        frozen_distance=float(frozen_d),
        marker_coordinate_error=per_marker,
        over_time=over_time,
        time=time,
        coverage=coverage,
    )


def simulator(scene, target: RecordingTarget):
    """params -> simulated marker positions (R, F, M, 3) of every recording of `target` at its
    frames, from its start states, driven particles along their markers (jit- and vmap-able)."""
    data = target_data(target)
    steps = target.steps

    def run(params):
        def one(times, filled, x0, v0):
            later = markers_simulated(scene.model, params, target, times, filled, x0, v0, steps, times[1:])
            return jnp.concatenate([x0[target.markers][None], later])

        return jax.vmap(one)(data["times"], data["filled"], data["states_x"][:, 0], data["states_v"][:, 0])

    return run


def predict(
    scene,
    values: dict,
    recordings,
    markers=None,
    driven=(),
    start: int = 1,
    smooth: int = 0,
    names=None,
    covariance=None,
    noise_std: float = 0.0,
    samples: int | None = None,
    seed: int = 0,
    marker_names=None,
) -> list[Prediction]:
    """Predict `recordings` with the fitted `values`, from their `start` frames, driven
    particles as recorded; with `samples` > 0 and the fit's `covariance` of the log values
    (a dict {"names": labels, "matrix": (P, P)}, see `Identifiability.covariance`), a 95%
    band from that many parameter sets (default 64 when a covariance is given) drawn from it
    and run as one batch, widened by +-1.96 `noise_std` (the observation noise). Markers are
    matched by name to `marker_names` (the fit's; see `recording_target`) where the recordings
    name them. A prediction that blows up is a BlowUpError; band draws that blow up are left
    out of the band and counted (`Prediction.band_unstable`).

    Example:
        >>> result = js.fit(scene, target, names)
        >>> out = js.predict(scene, result.final, [js.load_recording("held_out.h5")], driven=[0, 11])
        >>> out[0].mean_coordinate_error, out[0].mean_distance
    """
    names = tuple(names or (f"recording {i}" for i in range(len(recordings))))
    recordings = matched_by_name(list(recordings), names, marker_names)
    samples = (64 if covariance is not None else 0) if samples is None else int(samples)
    if samples and covariance is not None and samples < MIN_BAND_DRAWS:
        raise InputError(
            "bands", f"{samples} parameter set(s) cannot make a 95% band", f"draw at least {MIN_BAND_DRAWS} (e.g. 64)"
        )
    target = recording_target(scene, recordings, markers, driven, start, smooth, names=names)
    model = scene.model
    params = model.params_with(scene.params, {n: jnp.asarray(v) for n, v in values.items()})
    run = simulator(scene, target)
    what = f"predicting {len(recordings)} recording(s) of {target.frame_count} frames ({target.steps} steps)"
    fix = "predict fewer or shorter recordings (are the frame times in seconds?)"
    simulated = np.asarray(check_compiled(jax.jit(run), (params,), what, "recordings", fix)(params))
    for i in range(len(recordings)):
        _refuse_blowup(simulated[i, : int(target.lengths[i])], target, i, start)
    low = high = None
    unstable = 0
    if samples and covariance is not None:
        need = 3 * samples * simulated.nbytes  # the runs, their stable subset and the percentiles' sort
        check_memory(need, f"a band of {samples} parameter sets", "bands", "draw fewer parameter sets (e.g. 64)")
        draws = _draw(values, covariance, samples, seed)
        batch = jax.vmap(lambda v: model.params_with(scene.params, v))(draws)
        runs = np.asarray(jax.jit(jax.vmap(run))(batch))
        used = np.arange(runs.shape[2])[None, :] < np.asarray(target.lengths)[:, None]  # (R, F)
        stable = np.all(np.isfinite(runs) | ~used[None, :, :, None, None], axis=(1, 2, 3, 4))
        unstable = int(samples - stable.sum())
        if not stable.any():
            raise BlowUpError(
                f"every one of the {samples} parameter sets drawn for the band blew up (past the time step's "
                "stability limit); predict without a band, or fit with a smaller dt"
            )
        if stable.sum() < MIN_BAND_DRAWS:
            warnings.warn(
                f"the 95% band rests on {int(stable.sum())} of {samples} parameter sets ({unstable} blew up); "
                f"it is rough below {MIN_BAND_DRAWS}: draw more",
                BandWarning,
                stacklevel=2,
            )
        runs = runs[stable]
        widen = 1.96 * float(noise_std)
        low = np.percentile(runs, 2.5, axis=0) - widen
        high = np.percentile(runs, 97.5, axis=0) + widen
    out = []
    for i, rec in enumerate(recordings):
        used = int(target.lengths[i])
        x = np.array(rec.x)
        x[start:] = simulated[i, :used]
        seen = rec.x[start + 1 :]
        error = np.abs(x[start + 1 :] - seen)  # NaN where not seen
        frozen = np.repeat(rec.x[start : start + 1], rec.frame_count - start - 1, axis=0)
        frozen[:, carriers(target)] = seen[:, carriers(target)]
        frozen_error = np.abs(frozen - seen)
        both = np.isfinite(error).all(axis=-1) & np.isfinite(frozen_error).all(axis=-1)
        marker_seen = np.isfinite(error).all(axis=-1).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            per_marker = np.nansum(error, axis=(0, 2)) / (3 * marker_seen)
        band = {}
        if low is not None:
            lo, hi = np.array(rec.x), np.array(rec.x)
            lo[start:], hi[start:] = low[i, :used], high[i, :used]
            inside = (seen >= lo[start + 1 :]) & (seen <= hi[start + 1 :])
            band = {
                "low": lo,
                "high": hi,
                "coverage": float(inside[np.isfinite(seen)].mean()),
                "band_draws": samples,
                "band_unstable": unstable,
            }
        out.append(
            Prediction(
                name=target.names[i],
                t=np.asarray(rec.t),
                x=x,
                recorded=np.asarray(rec.x),
                start=start,
                mean_coordinate_error=_mean(error[np.isfinite(error)]),
                mean_distance=_mean(_norm(error)[np.isfinite(_norm(error))]),
                rms_error=float(np.sqrt(_mean(_norm(error)[np.isfinite(_norm(error))] ** 2))),
                marker_coordinate_error=per_marker,
                marker_seen=marker_seen,
                frozen_coordinate_error=_mean(frozen_error[both]),
                frozen_distance=_mean(_norm(frozen_error)[both]),
                marker_names=tuple(rec.markers),
                **band,
            )
        )
    return out


class BandWarning(UserWarning):
    """A prediction band drawn from fewer stable parameter sets than `MIN_BAND_DRAWS`."""


def _refuse_blowup(simulated: np.ndarray, target: RecordingTarget, i: int, start: int) -> None:
    """A BlowUpError naming the recording and frame where `simulated` (F, M, 3) of recording `i`
    stops being finite: a blown-up prediction is never written as markers not seen."""
    bad = ~np.isfinite(simulated).all(axis=(1, 2))
    if bad.any():
        frame = start + int(np.argmax(bad))
        raise BlowUpError(
            f"{target.names[i]}: the prediction blew up at frame {frame} (the values are past the time step's "
            "stability limit there, or a driven marker jumps); check the driven markers, or fit with a smaller dt"
        )


def _norm(error):
    return np.sqrt(np.sum(error**2, axis=-1))


def _mean(values) -> float:
    return float(np.mean(values)) if np.size(values) else float("nan")


def _draw(values: dict, covariance: dict, samples: int, seed: int) -> dict:
    """`samples` parameter sets: log values drawn from N(log values, covariance)."""
    labels = list(covariance["names"])
    matrix = np.asarray(covariance["matrix"], dtype=float)
    centre = np.concatenate([np.log(np.asarray(values[n], dtype=float)).reshape(-1) for n in unique_names(labels)])
    variance = np.diag(matrix).copy()
    matrix = np.where(np.isfinite(matrix), matrix, 0.0)
    # a value the data do not determine (an infinite or NaN variance) spreads as far as the cap below
    np.fill_diagonal(matrix, np.where(np.isfinite(variance), variance, 1e300))
    matrix = 0.5 * (matrix + matrix.T)
    # a parameter the data do not determine does not move the markers either: cap its log spread at 1
    scale = np.minimum(1.0, 1.0 / np.sqrt(np.maximum(np.diag(matrix), 1e-300)))
    eigenvalues, vectors = np.linalg.eigh(matrix * np.outer(scale, scale))
    matrix = (vectors * np.maximum(eigenvalues, 0.0)) @ vectors.T
    draws = np.random.default_rng(seed).multivariate_normal(centre, matrix, size=samples, method="eigh")
    out, column = {}, 0
    for n in unique_names(labels):
        size = int(np.size(values[n]))
        out[n] = jnp.asarray(np.exp(draws[:, column : column + size]).reshape((samples,) + np.shape(values[n])))
        column += size
    return out
