"""Pictures and movies of trajectories with matplotlib (y is drawn up)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .io.trajectory import atomic_path
from .resources import check_movie
from .sim.scene import Scene
from .sim.state import Trajectory

# World (x, y, z) with y up -> matplotlib's (x, y, z) with z up.
_TO_PLOT = (0, 2, 1)


def pyplot():
    """matplotlib.pyplot; on the non-interactive Agg backend (files only) unless pyplot is
    already in use (a notebook's inline figures stay as they are) or MPLBACKEND says otherwise."""
    import os
    import sys

    import matplotlib

    if "matplotlib.pyplot" not in sys.modules and not os.environ.get("MPLBACKEND"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, out, writer: str | None = None) -> Path:
    """Save `fig` to `out` atomically (format from the suffix) and close it; `writer` goes into a
    PNG's text chunk "writer" (what wrote it)."""
    out = Path(out)
    kind = out.suffix.lstrip(".").lower() or "png"
    metadata = {"writer": writer} if writer and kind == "png" else None
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format=kind, dpi=fig.dpi, metadata=metadata)
    pyplot().close(fig)
    return out


def render(
    scene: Scene,
    trajectory: Trajectory,
    out,
    frame: int = -1,
    max_frames: int = 60,
    progress=None,
    max_memory: int | None = None,
) -> Path:
    """Draw one frame to a PNG or the whole trajectory to a GIF, written atomically.

    Scenes with faces are drawn as a shaded triangle soup (jelly surface, cloth),
    others as points joined by their springs (mass_spring, chain).

    Args:
        out: a path ending in .png (one frame) or .gif (a movie).
        frame: which saved frame a PNG shows (negative counts from the end).
        max_frames: a GIF uses at most this many evenly spaced frames.
        progress: optional callable(done, total) for long movies.
        max_memory: refuse a movie whose pictures need more bytes than this (default: the
            memory available), before drawing any.

    Example:
        >>> scene, traj = js.load_trajectory("cloth.h5")
        >>> js.render(scene, traj, "cloth.png")
    """
    from matplotlib import animation

    plt = pyplot()

    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".png", ".gif"):
        raise InputError("out", f"{str(out)!r} is neither .png nor .gif", "name the output file.png or file.gif")
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1:
        raise InputError("max_frames", f"must be an integer >= 1, got {max_frames!r}", "give a positive frame count")
    x = np.asarray(trajectory.x)[..., _TO_PLOT]
    t = np.asarray(trajectory.t)
    frames = x.shape[0]
    if not -frames <= frame < frames:
        raise InputError("frame", f"{frame} is outside 0..{frames - 1}", "choose an existing frame")

    chosen = np.unique(np.linspace(0, frames - 1, min(max_frames, frames)).round().astype(int))
    drawn = chosen if suffix == ".gif" else np.array([frame % frames])
    broken = [int(k) for k in drawn if not np.isfinite(x[k]).all()]
    if broken:
        raise InputError(
            "file",
            f"frame {broken[0]} holds NaN or infinite positions ({len(broken)} of the {len(drawn)} frames drawn)",
            "draw earlier frames (--frame), or re-run the simulation at a stable dt",
        )
    width, height = 6 * 90, 5 * 90
    if suffix == ".gif":
        check_movie(len(chosen), width, height, max_memory)
    fig = plt.figure(figsize=(width / 90, height / 90), dpi=90)
    ax = fig.add_subplot(projection="3d")
    drawer = _Drawer(ax, scene, x, t)
    with atomic_path(out) as tmp:
        if suffix == ".png":
            drawer.draw(frame % frames)
            fig.savefig(tmp)
        else:
            movie = animation.FuncAnimation(fig, lambda i: drawer.draw(int(i)), frames=chosen, blit=False)
            movie.save(tmp, writer=animation.PillowWriter(fps=15), progress_callback=progress)
    plt.close(fig)
    return out


class _Drawer:
    def __init__(self, ax, scene: Scene, x: np.ndarray, t: np.ndarray):
        self.ax, self.scene, self.x, self.t = ax, scene, x, t
        finite = x[np.isfinite(x).all(axis=(1, 2))]
        lo, hi = (finite.min(axis=(0, 1)), finite.max(axis=(0, 1))) if finite.size else (np.zeros(3) - 1, np.ones(3))
        if scene.model.has("ground"):
            lo[2] = min(lo[2], float(scene.params.ground_height))
        centre, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 0.5) * 1.05
        self.limits = [(c - half, c + half) for c in centre]
        self.springs = np.asarray(scene.model.springs)
        self.pinned = np.asarray(scene.model.pinned)

    def draw(self, index: int):
        from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

        ax, p = self.ax, self.x[index]
        ax.clear()
        (xl, yl, zl) = self.limits
        ax.set(xlim=xl, ylim=yl, zlim=zl, xlabel="x [m]", ylabel="z [m]", zlabel="y [m]")
        ax.set_box_aspect((1, 1, 1))
        if self.scene.model.has("ground"):
            h = float(self.scene.params.ground_height)
            corners = [[xl[0], yl[0], h], [xl[1], yl[0], h], [xl[1], yl[1], h], [xl[0], yl[1], h]]
            ax.add_collection3d(Poly3DCollection([corners], facecolor="0.8", alpha=0.4, edgecolor="none"))
        if len(self.scene.faces):
            triangles = p[np.asarray(self.scene.faces)]
            ax.add_collection3d(
                Poly3DCollection(
                    triangles, facecolors="tab:orange", edgecolor="0.3", linewidth=0.15, alpha=0.9, shade=True
                )
            )
        else:
            if len(self.springs):
                ax.add_collection3d(Line3DCollection(p[self.springs], colors="0.4", linewidths=1.0))
            ax.scatter(*p[~self.pinned].T, s=18, color="tab:blue", depthshade=False)
        if self.pinned.any():
            ax.scatter(*p[self.pinned].T, s=30, color="black", marker="s", depthshade=False)
        ax.set_title(f"{self.scene.name}   t = {self.t[index]:.2f} s")
        return []


def plot_fit(result, out) -> Path:
    """Loss and parameter histories of a fit as a PNG, written atomically.

    Example:
        >>> js.fitting.plot_fit(result, "chain.fit.png")
    """
    plt = pyplot()

    out = Path(out)
    names = result.names
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(3.6 * (1 + len(names)), 3.4), dpi=90)
    iterations = np.arange(len(result.loss_history))
    axes[0].semilogy(iterations, np.maximum(result.loss_history, 1e-300), color="black")
    axes[0].set(xlabel="iteration", ylabel="loss [m²]", title="loss")
    changes = np.nonzero(np.diff(result.stage_of_iteration))[0] + 1
    for ax, name in zip(axes[1:], names):
        history = np.asarray(result.value_history[name]).reshape(len(iterations), -1).mean(axis=1)
        ax.plot(iterations, history, color="tab:blue", label="fit")
        if result.truth and name in result.truth:
            ax.axhline(float(np.mean(result.truth[name])), color="tab:green", linestyle="--", label="true")
            ax.legend(loc="best", fontsize=8)
        ax.set(xlabel="iteration", title=name)
    for ax in axes:
        for c in changes:
            ax.axvline(c, color="0.7", linewidth=0.8)
    fig.suptitle("fit: " + " -> ".join(f"{s.kind}({s.frames})" for s in result.stages), fontsize=9)
    fig.tight_layout()
    return save_figure(fig, out)


def plot_prediction(prediction, out, markers: int = 4, writer: str | None = None) -> Path:
    """Recorded against predicted marker heights (up to `markers` markers, with the 95% band
    where present) and the marker error against time, as a PNG written atomically.

    Example:
        >>> js.fitting.plot_prediction(js.predict(scene, values, [rec], driven=[0, 11])[0], "take1.png")
    """
    plt = pyplot()
    p = prediction
    fig, (paths, errors) = plt.subplots(1, 2, figsize=(11, 3.8), dpi=90)
    shown = np.unique(np.linspace(0, p.x.shape[1] - 1, min(markers, p.x.shape[1])).round().astype(int))
    for k, colour in zip(shown, plt.rcParams["axes.prop_cycle"].by_key()["color"]):
        paths.plot(p.t, p.recorded[:, k, 1], ".", color=colour, markersize=2, alpha=0.5)
        paths.plot(p.t[p.start :], p.x[p.start :, k, 1], color=colour, linewidth=1.2, label=f"marker {k}")
        if p.low is not None:
            paths.fill_between(p.t[p.start :], p.low[p.start :, k, 1], p.high[p.start :, k, 1], color=colour, alpha=0.2)
    paths.set(xlabel="t [s]", ylabel="y [m]", title=f"{p.name}: recorded (dots) and predicted")
    paths.legend(loc="best", fontsize=8)
    distance = np.linalg.norm(p.x - p.recorded, axis=-1)[p.start :]
    with np.errstate(invalid="ignore"):
        errors.plot(p.t[p.start :], 1e3 * np.nanmean(distance, axis=1), color="black", label="mean distance")
        errors.plot(
            p.t[p.start :], 1e3 * np.nanmax(distance, axis=1), color="tab:red", linewidth=0.8, label="worst marker"
        )
    errors.set(
        xlabel="t [s]",
        ylabel="distance [mm]",
        title=f"mean |error| {1e3 * p.mean_coordinate_error:.2f} mm per coordinate, {1e3 * p.mean_distance:.2f} mm distance",
    )
    errors.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, Path(out), writer)


def plot_error_summary(summary, predictions, out, writer: str | None = None) -> Path:
    """The pooled error of `predictions` (`summarise`) per marker (bars) and over time since the
    start (mean over recordings, with each recording's own curve faint), as a PNG written atomically.

    Example:
        >>> out = js.predict(scene, values, recordings, driven=[0, 1, 10, 11])
        >>> js.fitting.plot_error_summary(js.fitting.summarise(out), out, "errors.png")
    """
    plt = pyplot()
    fig, (bars, curve) = plt.subplots(1, 2, figsize=(11, 3.8), dpi=90)
    per_marker = 1e3 * summary.marker_coordinate_error
    names = predictions[0].marker_names or tuple(str(k) for k in range(per_marker.size))
    bars.bar(np.arange(per_marker.size), per_marker, color="tab:blue")
    bars.set_xticks(np.arange(per_marker.size), names, rotation=60 if per_marker.size > 8 else 0, fontsize=8)
    bars.axhline(1e3 * summary.mean_coordinate_error, color="black", linewidth=0.8, label="all markers")
    bars.set(ylabel="mean |error| per coordinate [mm]", title=f"per marker ({len(predictions)} recordings)")
    bars.legend(loc="best", fontsize=8)
    with np.errstate(invalid="ignore"):
        for p in predictions:
            e = p.coordinate_errors
            if e.size:
                curve.plot(summary.time[: e.shape[0]], 1e3 * np.nanmean(e, axis=(1, 2)), color="0.75", linewidth=0.6)
    curve.plot(summary.time, 1e3 * summary.over_time, color="black", label="mean over recordings")
    curve.set(
        xlabel="time since the start frame [s]",
        ylabel="mean |error| per coordinate [mm]",
        title=f"over time: {1e3 * summary.mean_coordinate_error:.2f} mm overall"
        f" ({1e3 * summary.mean_distance:.2f} mm distance)",
    )
    curve.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, Path(out), writer)
