"""Prediction: simulate recordings with fitted values, their error, and prediction bands."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .identifiability import unique_names
from .recording_loss import carriers, markers_simulated, target_data
from .recordings import RecordingTarget, recording_target


@dataclasses.dataclass(frozen=True)
class Prediction:
    """One recording predicted from its start frame.

    Attributes:
        name: the recording's name.
        t: frame times [s], (F,), the recording's.
        x: predicted marker positions [m], (F, M, 3); frames before `start` copied from the recording.
        recorded: the recording's marker positions (NaN where not seen).
        start: the first simulated frame.
        mean_absolute_error: mean distance [m] between predicted and seen markers after `start`.
        rms_error: root-mean-square of that distance [m].
        low, high: the 95% prediction band per marker, frame and axis (None without bands).
        coverage: the fraction of seen marker coordinates after `start` inside the band.
        frozen_error: the baseline: mean distance [m] when the free markers stay where they were
            at `start` and the driven ones move as recorded.
    """

    name: str
    t: np.ndarray
    x: np.ndarray
    recorded: np.ndarray
    start: int
    mean_absolute_error: float
    rms_error: float
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    coverage: float | None = None
    frozen_error: float | None = None


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
) -> list[Prediction]:
    """Predict `recordings` with the fitted `values`, from their `start` frames, driven
    particles as recorded; with `samples` > 0 and the fit's `covariance` of the log values
    (a dict {"names": labels, "matrix": (P, P)}, see `Identifiability.covariance`), a 95%
    band from that many parameter sets (default 64 when a covariance is given) drawn from it
    and run as one batch, widened by +-1.96 `noise_std` (the observation noise).

    Example:
        >>> result = js.fit(scene, target, names)
        >>> out = js.predict(scene, result.final, [js.load_recording("held_out.h5")], driven=[0, 11])
        >>> out[0].mean_absolute_error
    """
    recordings = list(recordings)
    target = recording_target(scene, recordings, markers, driven, start, smooth, names=names)
    model = scene.model
    params = model.params_with(scene.params, {n: jnp.asarray(v) for n, v in values.items()})
    run = simulator(scene, target)
    simulated = np.asarray(jax.jit(run)(params))
    low = high = None
    samples = (64 if covariance is not None else 0) if samples is None else int(samples)
    if samples and covariance is not None:
        draws = _draw(values, covariance, samples, seed)
        batch = jax.vmap(lambda v: model.params_with(scene.params, v))(draws)
        runs = np.asarray(jax.jit(jax.vmap(run))(batch))
        widen = 1.96 * float(noise_std)
        low = np.percentile(runs, 2.5, axis=0) - widen
        high = np.percentile(runs, 97.5, axis=0) + widen
    out = []
    for i, rec in enumerate(recordings):
        used = int(target.lengths[i])
        x = np.array(rec.x)
        x[start:] = simulated[i, :used]
        d = np.linalg.norm(x[start + 1 :] - rec.x[start + 1 :], axis=-1)
        frozen = np.repeat(rec.x[start : start + 1], rec.frame_count - start - 1, axis=0)
        frozen[:, carriers(target)] = rec.x[start + 1 :, carriers(target)]
        baseline = np.linalg.norm(frozen - rec.x[start + 1 :], axis=-1)
        baseline = baseline[np.isfinite(d) & np.isfinite(baseline)]
        d = d[np.isfinite(d)]
        band = {}
        if low is not None:
            lo, hi = np.array(rec.x), np.array(rec.x)
            lo[start:], hi[start:] = low[i, :used], high[i, :used]
            seen = rec.x[start + 1 :]
            inside = (seen >= lo[start + 1 :]) & (seen <= hi[start + 1 :])
            band = {"low": lo, "high": hi, "coverage": float(inside[np.isfinite(seen)].mean())}
        out.append(
            Prediction(
                name=target.names[i],
                t=np.asarray(rec.t),
                x=x,
                recorded=np.asarray(rec.x),
                start=start,
                mean_absolute_error=float(d.mean()) if d.size else float("nan"),
                rms_error=float(np.sqrt(np.mean(d**2))) if d.size else float("nan"),
                frozen_error=float(baseline.mean()) if baseline.size else float("nan"),
                **band,
            )
        )
    return out


def _draw(values: dict, covariance: dict, samples: int, seed: int) -> dict:
    """`samples` parameter sets: log values drawn from N(log values, covariance)."""
    labels = list(covariance["names"])
    matrix = np.asarray(covariance["matrix"], dtype=float)
    centre = np.concatenate([np.log(np.asarray(values[n], dtype=float)).reshape(-1) for n in unique_names(labels)])
    matrix = np.where(np.isfinite(matrix), matrix, 0.0)
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
