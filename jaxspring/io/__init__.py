"""Files: scenes, trajectories, recordings, experiments, fit files and cable scenes.

`js.io` holds the readers and writers beyond the everyday ones, which are also top-level
(`load_scene`, `save_trajectory`, `load_recording`, ...).

Example:
    >>> import jaxspring as js
    >>> progress = js.io.load_fit_progress("fit.h5")
"""

import importlib

# Read lazily (PEP 562): the readers build on jaxspring.fit, which reads files with them.
_HOME = {
    "CableModel": "cable",
    "cable_scene": "cable",
    "Experiment": "experiment",
    "load_experiment": "experiment",
    "observations_from_file": "experiment",
    "load_fit_progress": "fit_file",
    "save_fit": "fit_file",
    "Recording": "recording",
    "load_recording": "recording",
    "save_recording": "recording",
    "builtin_scenes": "scene",
    "load_scene": "scene",
    "scene_from_dict": "scene",
    "load_trajectory": "trajectory",
    "save_trajectory": "trajectory",
}


def __getattr__(name: str):
    if name in _HOME:
        return getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(__all__)


__all__ = [
    "load_scene",
    "scene_from_dict",
    "builtin_scenes",
    "save_trajectory",
    "load_trajectory",
    "Recording",
    "load_recording",
    "save_recording",
    "Experiment",
    "load_experiment",
    "observations_from_file",
    "save_fit",
    "load_fit_progress",
    "CableModel",
    "cable_scene",
]
