"""Fit files (HDF5, docs/file-formats.md): results, histories and the state needed to resume."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np

from ..errors import FileFormatError, InputError
from ..fit.identifiability import Identifiability, unique_names
from ..fit.plan import PLAN_VERSION
from ..fit.progress import FitProgress
from ..fit.recording_loss import NUISANCE
from ..fit.results import FitResult
from ..fit.settings import Stage
from .trajectory import atomic_path, open_hdf5

FIT_FORMAT = "jaxspring.fit"
FIT_FORMAT_VERSION = 1


def save_fit(
    path,
    config: dict,
    names,
    initial: dict,
    progress: FitProgress,
    result: FitResult | None = None,
    prediction: dict | None = None,
) -> None:
    """Write a single-member fit (checkpoint or final) atomically.

    `config` (JSON-able) identifies the fit; `--resume` refuses a file whose config differs.
    `prediction` (JSON-able: scene file text, markers, driven, start, smooth) is what
    `jaxspring predict` needs besides the fitted values.

    Example:
        >>> save_fit("chain.fit.h5", config, result.names, result.initial, progress, result)
    """
    from ..version import __version__

    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(
            format=FIT_FORMAT,
            format_version=FIT_FORMAT_VERSION,
            jaxspring_version=__version__,
            config=json.dumps(config, sort_keys=True),
            done=bool(progress.done),
        )
        if prediction is not None:
            f.attrs["prediction"] = json.dumps(prediction, sort_keys=True)
        group = f.create_group("fit")
        final = result.final if result is not None else {n: np.exp(np.asarray(progress.theta[n])[0]) for n in names}
        group.create_group("initial").attrs.update({n: np.asarray(initial[n]) for n in names})
        group.create_group("final").attrs.update({n: np.asarray(final[n]) for n in names})
        history = group.create_group("history")
        history.create_dataset("loss", data=np.array([np.asarray(v)[0] for v in progress.loss], dtype=float))
        history.create_dataset("stage", data=np.asarray(progress.stage_of_iteration, dtype=np.int32))
        for n in names:
            values = [np.asarray(v)[0] for v in progress.values[n]]
            history.create_dataset(n, data=np.array(values, dtype=float).reshape((len(values),) + np.shape(initial[n])))
        optimizer = group.create_group("optimizer")
        optimizer.attrs.update(
            stage=progress.stage, iteration=progress.iteration, wall_s=progress.wall_s, plan_version=PLAN_VERSION
        )
        if progress.last_step is not None:
            optimizer.create_dataset("last_step", data=np.asarray(progress.last_step))
        if progress.horizon is not None:
            optimizer.attrs["horizon"] = int(progress.horizon)
        if progress.refit_frames is not None:
            optimizer.attrs["refit_frames"] = int(progress.refit_frames)
        if progress.plan is not None:  # the stages as the fit's transitions left them
            optimizer.attrs["plan"] = json.dumps([[s.kind, int(s.frames), s.spread] for s in progress.plan])
        retreats = [int(i) for i, moved in progress.retreats if np.asarray(moved)[0]]  # the file's member's
        if retreats:
            optimizer.attrs["retreats"] = retreats
        theta = optimizer.create_group("theta")
        for n in progress.theta:  # the log parameters, and a fitted start state and driven paths
            theta.create_dataset(n, data=np.asarray(progress.theta[n]))
        if progress.optimizer_leaves is not None:
            leaves = optimizer.create_group("state")
            for i, leaf in enumerate(progress.optimizer_leaves):
                leaves.create_dataset(f"{i:05d}", data=np.asarray(leaf))
        if result is not None:
            group.attrs["final_loss"] = result.final_loss
            if result.truth:
                group.create_group("true").attrs.update({n: np.asarray(v) for n, v in result.truth.items()})
            ident = result.identifiability
            if ident is not None:
                group.create_group("standard_error").attrs.update(
                    {n: np.asarray(v) for n, v in ident.standard_error.items()}
                )
                corr = group.create_dataset("correlation", data=ident.correlation)
                corr.attrs["names"] = list(ident.names)
                group.attrs["noise_std"] = float(ident.noise_std)
                group.attrs["warnings"] = json.dumps(list(ident.warnings))


def load_fit_progress(path, config: dict, names) -> FitProgress:
    """Read the resumable state of a fit file written for the same `config`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("--resume", f"{path} does not exist", "run the fit once without --resume")
    with open_hdf5(path, "delete it and fit again without --resume") as f:
        if f.attrs.get("format") != FIT_FORMAT:
            raise FileFormatError(f"{path}: not a jaxspring fit file; choose another --out")
        saved = json.loads(f.attrs["config"])
        if saved != json.loads(json.dumps(config, sort_keys=True)):
            config = json.loads(json.dumps(config, sort_keys=True))
            changed = []
            for k in sorted(set(saved) | set(config)):
                old, new = saved.get(k), config.get(k)
                if old != new and isinstance(old, dict) and isinstance(new, dict):  # name the files that changed
                    parts = sorted(n for n in set(old) | set(new) if old.get(n) != new.get(n))
                    changed.append(f"{k} of {', '.join(parts)}")
                elif old != new:
                    changed.append(k)
            raise InputError(
                "--resume",
                f"{path} was written by a different fit (differs in {', '.join(changed)})",
                "repeat the original command, or drop --resume to start over",
            )
        group = f["fit"]
        history = group["history"]
        optimizer = group["optimizer"]
        if int(optimizer.attrs.get("plan_version", 1)) != PLAN_VERSION:
            raise InputError(
                "--resume",
                f"{path} was written by a jaxspring that planned a fit's stages otherwise",
                "drop --resume to fit again from the start",
            )
        loss = [np.array([v]) for v in history["loss"][()]]
        values = {n: [np.asarray(v)[None] for v in history[n][()]] for n in names}
        leaves = None
        if "state" in optimizer:
            leaves = [optimizer["state"][k][()] for k in sorted(optimizer["state"])]
        return FitProgress(
            stage=int(optimizer.attrs["stage"]),
            iteration=int(optimizer.attrs["iteration"]),
            theta={n: jnp.asarray(optimizer["theta"][n][()]) for n in [*names, *NUISANCE] if n in optimizer["theta"]},
            optimizer_leaves=leaves,
            loss=loss,
            values=values,
            stage_of_iteration=[int(s) for s in history["stage"][()]],
            last_step=optimizer["last_step"][()] if "last_step" in optimizer else None,
            done=bool(f.attrs["done"]),
            wall_s=float(optimizer.attrs["wall_s"]),
            horizon=int(optimizer.attrs["horizon"]) if "horizon" in optimizer.attrs else None,
            refit_frames=int(optimizer.attrs["refit_frames"]) if "refit_frames" in optimizer.attrs else None,
            retreats=[(int(i), np.array([True])) for i in optimizer.attrs.get("retreats", [])],
            plan=[Stage(*s) for s in json.loads(optimizer.attrs["plan"])] if "plan" in optimizer.attrs else None,
        )


def load_fitted(path) -> dict:
    """What prediction needs from a finished fit file: {"final": name -> value,
    "prediction": the saved prediction dict, "covariance": {"names", "matrix"} of the log
    values or None, "noise_std": the fit's residual standard deviation [m] (0 if unknown)}.

    Example:
        >>> fitted = load_fitted("rope.fit.h5"); fitted["final"]
    """
    path = Path(path)
    if not path.exists():
        raise FileFormatError(f"{path}: file not found; give a fit file written by `jaxspring fit`")
    if not path.is_file():
        raise FileFormatError(f"{path}: not a regular file; give a fit file written by `jaxspring fit`")
    with open_hdf5(path, "fit again with `jaxspring fit`") as f:
        if f.attrs.get("format") != FIT_FORMAT:
            raise FileFormatError(f"{path}: not a jaxspring fit file; give one written by `jaxspring fit`")
        if not bool(f.attrs.get("done", False)):
            raise InputError("fit", f"{path} is an unfinished fit", "finish it with `jaxspring fit ... --resume`")
        if "prediction" not in f.attrs:
            raise InputError(
                "fit", f"{path} was not fitted to recordings", "fit an experiment with [target] recordings first"
            )
        try:
            group = f["fit"]
            final = {n: np.asarray(v, dtype=float) for n, v in group["final"].attrs.items()}
            prediction = json.loads(f.attrs["prediction"])
            covariance = None
            if "correlation" in group and "standard_error" in group:
                labels = [str(n) for n in group["correlation"].attrs["names"]]
                relative = {
                    n: np.asarray(group["standard_error"].attrs[n] / final[n], dtype=float)
                    for n in unique_names(labels)
                }
                report = Identifiability({}, relative, group["correlation"][()], tuple(labels), 0.0, ())
                covariance = report.covariance()
            noise_std = float(group.attrs.get("noise_std", 0.0))
        except (KeyError, TypeError, ValueError, OSError) as exc:
            raise FileFormatError(
                f"{path}: a part of the fit is missing or unreadable ({type(exc).__name__}: {exc}); fit again"
            ) from None
        bad = [n for n, v in final.items() if not (np.all(np.isfinite(v)) and np.all(v > 0))]
        if bad or not final:
            raise InputError(
                "fit",
                f"{path} holds no positive finite fitted value for {', '.join(bad) or 'any parameter'}",
                "fit again",
            )
        return {
            "final": final,
            "prediction": prediction,
            "covariance": covariance,
            "noise_std": noise_std if np.isfinite(noise_std) else 0.0,
        }
