"""Recordings as a fit's target: markers seen at camera frames, some particles driven.

`recording_target` turns recordings of one object (`Recording`s, any lengths and frame
times) into one padded batch: every recording starts at its frame `start`, its driven
particles follow their markers, and the misfit is taken only where a marker was seen,
at the frames' own times (simulated positions interpolated linearly between steps).

The start state: a particle carrying a marker starts at the marker; the others at the
scene's positions moved by the rigid motion that best matches the markers (least
squares, Kabsch), plus the markers' remaining displacements spread by inverse-square
distance weights in the scene's configuration (so they follow a bent rope, and a
rigidly moved object exactly). Velocities are the backward difference of that rule
between frames start - 1 and start (zero when start is 0). Markers lost for a few
frames are interpolated linearly in time for the start states and driven paths.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..io.recording import matched_by_name
from ..sim.checks import particle_indices, whole_number
from ..sim.driven import steps_to_reach
from ..sim.state import State

LOSSES = ("mse", "l1", "huber")


@dataclasses.dataclass(frozen=True, eq=False)
class RecordingTarget:
    """Recordings of one object prepared as one fit target (see `recording_target`).

    Attributes (R recordings, F frames from `start` on, padded; M markers, N particles):
        names: the recordings' names.
        markers: particle carrying each marker, int (M,).
        driven: driven particles, int (D,), each carrying a marker.
        start: the frame each simulation starts from.
        times: frame times from the start frame [s], (R, F); padding adds tiny steps after the last.
        x: marker positions (R, F, M, 3), NaN where not seen and in padding.
        filled: the markers' paths (R, F, M, 6): positions with gaps interpolated in time (or
            smoothed, see `smooth`) and, after them, velocities; start states and driven paths
            come from it (driven paths linear between frames, or with `smooth` > 0 cubic
            Hermite through the smoothed positions and velocities).
        states_x, states_v: start-rule states of all particles at every frame, (R, F, N, 3).
        lengths: frames of each recording from `start` on, int (R,).
        dt: the scene's time step.
        loss: "mse", "l1" or "huber"; huber_scale: Huber's transition [m].
        fit_start: fit each recording's start state (see `recording_target`).
        fit_driven: fit each recording's driven paths too (see `recording_target`).
        free: particles neither pinned nor driven, bool (N,).
        marker_names: the markers' names, in the order of `markers` (the recordings' columns
            are matched to them by name).
    """

    names: tuple
    markers: np.ndarray
    driven: np.ndarray
    start: int
    times: np.ndarray
    x: np.ndarray
    filled: np.ndarray
    states_x: np.ndarray
    states_v: np.ndarray
    lengths: np.ndarray
    dt: float
    loss: str = "mse"
    huber_scale: float = 0.002
    smooth: int = 0
    noise_std: float = 0.0
    truth: dict | None = None
    save_every: int = 1
    fit_start: bool = False
    free: np.ndarray | None = None
    fit_driven: bool = False
    marker_names: tuple = ()

    @property
    def frame_count(self) -> int:
        return int(self.x.shape[1])

    @property
    def steps(self) -> int:
        return steps_to_reach(float(self.times[:, -1].max()), self.dt)

    @property
    def full(self) -> bool:
        """False: no recorded full states; strategy "auto" fits recordings over their whole
        length (see `plan_stages`): segment starts estimated from noisy markers bias short
        segments (measured: a 34-particle rope's shooting stage walked to a point the full
        horizon could not leave)."""
        return False

    shootable = True  # strategy "shooting" starts its segments from the start rule

    @property
    def seen(self) -> np.ndarray:
        return np.isfinite(self.x).all(axis=-1)

    @property
    def residual_count(self) -> int:
        """Residual values that carry data (seen markers after the start frame, x3; from
        the start frame on when the start state is fitted)."""
        return int(self.seen[:, 0 if self.fit_start else 1 :].sum()) * 3

    @property
    def initial_state(self) -> State:
        return State(x=jnp.asarray(self.states_x[:, 0]), v=jnp.asarray(self.states_v[:, 0]))


def recording_target(
    scene,
    recordings,
    markers=None,
    driven=(),
    start=1,
    smooth=0,
    loss="mse",
    huber_scale=0.002,
    names=None,
    fit_start=False,
    fit_driven=False,
    marker_names=None,
):
    """Prepare `recordings` (a list of `Recording`) of `scene` as one fit target.

    Markers are matched by name where the recordings name them (not the default m0, m1, ...):
    every recording's markers are taken in the order of `marker_names` (default: the first
    recording's), whatever the order of its columns; a recording without one of them is refused.

    Args:
        markers: particle carrying marker k (default: particle k).
        driven: particles moved as their markers were recorded (each must carry a marker).
        start: frame the simulations start from (x there; v by backward difference).
        smooth: 0 (default): start states and driven paths from the markers as recorded. K > 0:
            from a least-squares quadratic in time through the 2K + 1 frames around each frame
            (seen ones), its value and slope: against noise on every frame, which a backward
            difference turns into velocity errors of ~1.4 noise / frame interval.
        loss: "mse" (default), "l1" or "huber" (quadratic below `huber_scale` [m], linear above).
        fit_start: also fit every recording's start state (the free particles' positions and
            velocities, as corrections to the start rule's), with the start frame's markers
            in the misfit: noise in the start frame's markers otherwise sets off motion
            (measured: +13% on a rope's kd from 1 mm noise) that damping is fitted to hide.
        fit_driven: also fit every recording's driven paths (a correction to each driven
            marker's position at every frame; paths linear between frames) and the start
            state (implies `fit_start`), with the driven markers in the misfit: noise on
            the driven markers is otherwise noise in the force that moves the object,
            which the parameters are fitted to explain (measured on a 6-particle rope,
            1 mm noise, 10 noise seeds: kd 7-31% off with standard errors of 1-2%).

    Example:
        >>> target = recording_target(scene, [js.load_recording("take1.h5")], driven=[0, 11])
        >>> result = js.fit(scene, target, ["ks.stretch", "kd.stretch", "cd"])
    """
    recordings = list(recordings)
    names = tuple(names or (f"recording {i}" for i in range(len(recordings))))
    if not recordings:
        raise InputError("recordings", "none given", "give at least one recording file")
    count = recordings[0].marker_count
    for name, rec in zip(names, recordings):
        if rec.marker_count != count:
            raise InputError(
                "recordings",
                f"{name} has {rec.marker_count} markers but {names[0]} has {count} (differ in marker count)",
                "fit recordings of one setup",
            )
    recordings = matched_by_name(recordings, names, marker_names)
    model = scene.model
    n = model.particle_count
    markers = (
        np.arange(count)
        if markers is None
        else particle_indices("markers", markers, n, "give indices of the scene's particles")
    )
    if markers.size != count:
        raise InputError(
            "markers",
            f"lists {markers.size} particles but the recordings have {count} markers",
            "give one particle per marker",
        )
    if np.unique(markers).size != markers.size:
        raise InputError("markers", "puts two markers on one particle", "give each marker its own particle")
    driven = particle_indices("driven", driven, n, "give indices of the scene's particles")
    if np.unique(driven).size != driven.size:
        twice = next(int(p) for k, p in enumerate(driven) if p in driven[:k])
        raise InputError("driven", f"names particle {twice} twice", "give each driven particle once")
    carried = [int(np.nonzero(markers == p)[0][0]) if p in markers else -1 for p in driven]
    if -1 in carried:
        raise InputError(
            "driven", f"particle {driven[carried.index(-1)]} carries no marker", "drive particles that carry markers"
        )
    if np.asarray(model.pinned)[driven].any():
        raise InputError("driven", "names a pinned particle", "a particle is either pinned or driven")
    if loss not in LOSSES:
        raise InputError("loss", f"unknown loss {loss!r}", f"use one of {', '.join(LOSSES)}")
    if not (np.isfinite(huber_scale) and huber_scale > 0):
        raise InputError("huber_scale", "must be a positive length [m]", "set e.g. huber_scale = 0.002")
    start, smooth = whole_number("start", start), whole_number("smooth", smooth)
    if smooth < 0:
        raise InputError("smooth", f"must be >= 0, got {smooth}", "give 0 (no smoothing) or a half-window such as 5")
    for name, rec in zip(names, recordings):
        if not 0 <= start < rec.frame_count - 1:
            raise InputError(
                "start",
                f"frame {start} is not before the last frame of {name} ({rec.frame_count} frames)",
                "start earlier",
            )
        if 2 * smooth + 1 > rec.frame_count:
            raise InputError(
                "smooth",
                f"a window of {2 * smooth + 1} frames is longer than {name} ({rec.frame_count} frames)",
                "smooth over fewer frames (e.g. smooth = 5)",
            )
        steps = (rec.t[-1] - rec.t[start]) / model.dt
        if steps > MAX_STEPS:
            raise InputError(
                "recordings",
                f"{name} spans {rec.t[-1] - rec.t[start]:.3g} s from its start frame, {steps:.3g} time steps of "
                f"{model.dt:g} s",
                "give frame times in seconds (convert nanoseconds or milliseconds), or a larger dt",
            )
    frames = max(r.frame_count for r in recordings) - start
    dtype = np.dtype(model.mass.dtype)
    rest = np.asarray(scene.state.x, dtype=float)
    shape = (len(recordings), frames)
    times, x, filled = np.zeros(shape), np.full(shape + (count, 3), np.nan), np.zeros(shape + (count, 6))
    states_x, states_v = np.zeros(shape + (n, 3)), np.zeros(shape + (n, 3))
    lengths = np.zeros(len(recordings), dtype=np.int64)
    for i, (name, rec) in enumerate(zip(names, recordings)):
        gapless = _fill_gaps(name, rec, driven_markers=carried, start=start)
        used = rec.frame_count - start
        lengths[i] = used
        times[i, :used] = rec.t[start:] - rec.t[start]
        times[i, used:] = times[i, used - 1] + 1e-3 * model.dt * np.arange(1, frames - used + 1)  # still increasing
        x[i, :used] = rec.x[start:]
        positions, velocities = _smoothed(rec.t, gapless, rec.seen, int(smooth))
        for j in range(used):
            here, rate = positions[start + j], velocities[start + j]
            states_x[i, j] = spread(rest, markers, here)
            states_v[i, j] = (spread(rest, markers, here + 1e-3 * rate) - states_x[i, j]) / 1e-3
        filled[i, :used] = np.concatenate([positions, velocities], axis=-1)[start:]
        filled[i, used:] = np.concatenate([positions[-1], 0.0 * velocities[-1]], axis=-1)
        states_x[i, used:] = states_x[i, used - 1]
    free = ~(np.asarray(model.pinned, dtype=bool) | np.isin(np.arange(n), driven))
    if (fit_start or fit_driven) and not free.any():
        field = "fit_driven" if fit_driven else "fit_start"
        raise InputError(
            field, "every particle is pinned or driven: no start state is left to fit", f"set {field} = false"
        )
    return RecordingTarget(
        names=names,
        markers=markers,
        driven=driven,
        start=start,
        times=times.astype(dtype),
        x=x.astype(dtype),
        filled=filled.astype(dtype),
        states_x=states_x.astype(dtype),
        states_v=states_v.astype(dtype),
        lengths=lengths,
        dt=float(model.dt),
        loss=loss,
        huber_scale=float(huber_scale),
        smooth=int(smooth),
        fit_start=bool(fit_start or fit_driven),
        fit_driven=bool(fit_driven),
        free=free,
        marker_names=tuple(recordings[0].markers),
    )


MAX_STEPS = 2**31 - 1
"""Most time steps a recording may span from its start frame (a step count is a 32-bit integer)."""


def _smoothed(t, x, seen, half: int):
    """(positions, velocities) (F, M, 3) of gap-filled markers `x`: as recorded with backward
    differences (frame 0 at rest) when `half` is 0, else each frame's least-squares quadratic
    through the seen frames within `half` frames either side, evaluated there."""
    if half == 0:
        velocities = np.zeros_like(x)
        velocities[1:] = np.diff(x, axis=0) / np.diff(t)[:, None, None]
        return x, velocities
    count = t.shape[0]
    positions, velocities = np.empty_like(x), np.empty_like(x)
    for j in range(count):
        window = np.arange(max(j - half, 0), min(j + half + 1, count))
        h = t[window] - t[j]
        basis = np.stack([np.ones_like(h), h, h * h], axis=1)  # (W, 3)
        weight = np.where(seen[window], 1.0, 1e-3)  # (W, M); gaps count a little (filled)
        normal = np.einsum("wm,wa,wb->mab", weight, basis, basis) + 1e-12 * np.eye(3)
        rhs = np.einsum("wm,wa,wmk->mak", weight, basis, x[window])
        coefficients = np.linalg.solve(normal, rhs)  # (M, 3 coefficients, 3 axes)
        positions[j], velocities[j] = coefficients[:, 0], coefficients[:, 1]
    return positions, velocities


def _fill_gaps(name, rec, driven_markers, start) -> np.ndarray:
    """Marker positions with every gap interpolated linearly in time; a driven marker lost at
    the first used frame or the last is an error (its path there is unknown)."""
    x = np.array(rec.x)
    seen = rec.seen
    first = max(start - 1, 0)
    for k in range(rec.marker_count):
        ok = seen[:, k]
        if k in driven_markers and not (ok[first : start + 1].all() and ok[-1]):
            lost = np.nonzero(~ok)[0]
            edge = lost[(lost <= start) | (lost >= rec.frame_count - 1)]
            label = rec.markers[k]
            raise InputError(
                "driven",
                f"driven marker {label!r} of {name} is not seen at frame(s) {', '.join(map(str, edge[:5]))}",
                "start later, or trim the recording to frames where the driven markers are seen",
            )
        if not ok.all():
            for axis in range(3):
                x[~ok, k, axis] = np.interp(rec.t[~ok], rec.t[ok], rec.x[ok, k, axis])
    return x


def spread(rest: np.ndarray, markers: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """All particles' positions from marker positions `seen` (M, 3) by the start rule
    (module docstring): markers exact, rigid best fit plus inverse-square-distance
    weighted marker displacements elsewhere."""
    anchor = rest[markers]
    if markers.size >= 3:
        ca, cs = anchor.mean(axis=0), seen.mean(axis=0)
        u, _, vt = np.linalg.svd((anchor - ca).T @ (seen - cs))
        flip = np.sign(np.linalg.det(u @ vt)) or 1.0
        rotation = (u @ np.diag([1.0, 1.0, flip]) @ vt).T
        moved = (rest - ca) @ rotation.T + cs
    else:
        moved = rest + (seen - anchor).mean(axis=0)
    residual = seen - moved[markers]
    distance2 = np.sum((rest[:, None, :] - anchor[None]) ** 2, axis=-1)
    weights = 1.0 / np.maximum(distance2, 1e-300)
    weights /= weights.sum(axis=1, keepdims=True)
    out = moved + weights @ residual
    out[markers] = seen
    return out


def driven_noise(target: RecordingTarget) -> float:
    """The driven markers' noise [m] (RMS per coordinate), estimated from their seen frames'
    fourth differences in time, where white noise of variance s^2 gives variance 70 s^2 and a
    path moving smoothly at the frame rate nearly nothing. 0 without driven particles."""
    if len(target.driven) == 0:
        return 0.0
    carried = [int(np.nonzero(target.markers == p)[0][0]) for p in target.driven]
    x = target.x[:, :, carried]  # (R, F, D, 3), NaN where unseen
    fourth = x[:, 4:] - 4 * x[:, 3:-1] + 6 * x[:, 2:-2] - 4 * x[:, 1:-3] + x[:, :-4]
    fourth = fourth[np.isfinite(fourth)]
    return float(np.sqrt(np.mean(fourth**2) / 70.0)) if fourth.size else 0.0


def warn_of_noisy_driven_paths(target: RecordingTarget, ident):
    """The report with a warning when the driven markers are about as noisy as the fit's
    residuals: held as recorded, their noise pushes the object in every simulation and the
    parameters are fitted to explain it, beyond what the standard errors say."""
    noise = driven_noise(target)
    if noise < 0.3 * ident.noise_std:
        return ident
    warning = (
        f"the driven markers are noisy (~{noise * 1e3:.2g} mm, fourth differences) and their paths are held as "
        "recorded: that noise moves the object in the fit, biasing the values beyond these standard errors; "
        "fit the paths too (fit_driven)"
    )
    return dataclasses.replace(ident, warnings=ident.warnings + (warning,))
