"""Trajectory files: exact round trip, the DESIGN.md layout, atomic writes, clear errors."""

import os

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxspring as js
from jaxspring.io.trajectory import atomic_path


@pytest.fixture(scope="module")
def jelly_run(scenes):
    scene = scenes["jelly"]
    return scene, js.rollout(scene.model, scene.params, scene.state, steps=100, save_every=20)


def test_round_trip_is_exact(tmp_path, jelly_run):
    scene, traj = jelly_run
    path = tmp_path / "jelly.h5"
    js.save_trajectory(path, scene, traj)
    loaded_scene, loaded = js.load_trajectory(path)
    for a, b in ((traj.x, loaded.x), (traj.v, loaded.v), (traj.t, loaded.t)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert loaded_scene.model.terms == scene.model.terms
    assert loaded_scene.model.dt == scene.model.dt and loaded_scene.model.integrator == scene.model.integrator
    for name, value in scene.params.to_dict().items():
        np.testing.assert_array_equal(np.asarray(getattr(loaded_scene.params, name)), np.asarray(value))
    for field in ("springs", "rest_length", "mass", "pinned", "drag"):
        np.testing.assert_array_equal(
            np.asarray(getattr(loaded_scene.model, field)), np.asarray(getattr(scene.model, field))
        )
    np.testing.assert_array_equal(loaded_scene.faces, scene.faces)
    # the rebuilt scene continues the same physics
    again = js.rollout(loaded_scene.model, loaded_scene.params, loaded_scene.state, steps=100, save_every=20)
    np.testing.assert_array_equal(np.asarray(again.x), np.asarray(traj.x))


def test_layout_matches_design(tmp_path, scenes):
    scene = scenes["mass_spring"]
    traj = js.rollout(scene.model, scene.params, scene.state, steps=10, save_every=5)
    path = tmp_path / "pair.h5"
    js.save_trajectory(path, scene, traj)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "jaxspring.trajectory" and f.attrs["format_version"] == 1
        for key in ("scene", "integrator", "dt", "dtype", "jaxspring_version"):
            assert key in f.attrs
        assert sorted(f["params"]) == ["gravity", "kd", "ks"]  # no drag, no ground
        assert f["topology/springs"].dtype == np.int32 and f["topology/springs"].shape == (1, 2)
        assert f["topology/pinned"].dtype == bool and f["topology/drag"].dtype == bool
        assert f["trajectory/x"].shape == (3, 2, 3) and f["trajectory/t"].shape == (3,)
        np.testing.assert_allclose(f["trajectory/t"][()], [0.0, 0.005, 0.01])


def test_interrupted_write_leaves_nothing(tmp_path):
    target = tmp_path / "out.h5"
    target.write_bytes(b"previous contents")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            with open(tmp, "wb") as handle:
                handle.write(b"half")
            raise RuntimeError("killed")
    assert target.read_bytes() == b"previous contents"
    assert os.listdir(tmp_path) == ["out.h5"]


def test_missing_truncated_and_foreign_files(tmp_path, jelly_run):
    scene, traj = jelly_run
    with pytest.raises(js.FileFormatError, match="not found"):
        js.load_trajectory(tmp_path / "nope.h5")
    good = tmp_path / "good.h5"
    js.save_trajectory(good, scene, traj)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(js.FileFormatError, match="truncated|incomplete"):
        js.load_trajectory(truncated)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.create_dataset("data", data=np.arange(3))
    with pytest.raises(js.FileFormatError, match="not a jaxspring trajectory"):
        js.load_trajectory(foreign)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(js.FileFormatError, match="not a readable HDF5"):
        js.load_trajectory(text)


def test_custom_topology_round_trip(tmp_path):
    """A scene that is not one of the four: explicit particles, per-spring stiffness."""
    doc = {
        "dt": 0.001,
        "steps": 40,
        "save_every": 20,
        "physics": {"ks": [100.0, 200.0, 300.0], "kd": 0.5, "cd": 0.01},
        "particles": {
            "x": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
            "pinned": [0],
            "drag": [False, True, True, True],
        },
        "springs": {"pairs": [[0, 1], [1, 2], [2, 3]]},
    }
    scene = js.scene_from_dict(doc)
    traj = js.rollout(scene.model, scene.params, scene.state, steps=40, save_every=20)
    js.save_trajectory(tmp_path / "custom.h5", scene, traj)
    loaded, again = js.load_trajectory(tmp_path / "custom.h5")
    np.testing.assert_array_equal(np.asarray(loaded.params.ks), [100.0, 200.0, 300.0])
    np.testing.assert_array_equal(np.asarray(loaded.model.drag), [False, True, True, True])
    assert jnp.all(again.x == traj.x)


def test_a_fit_file_keeps_the_plan_its_transitions_left(tmp_path):
    """A checkpoint keeps the stages as they stand (here a final stage cut to segments and a
    refit added, as the fit's transitions leave them), and `--resume` reads back exactly those."""
    from jaxspring.fit.progress import FitProgress
    from jaxspring.fit.settings import Stage
    from jaxspring.io.fit_file import load_fit_progress, save_fit

    plan = [Stage("shooting", 10), Stage("ensemble", 50, 0.1), Stage("position_shooting", 10)]
    progress = FitProgress(1, 0, {"ks": np.zeros(1)}, None, [], {"ks": []}, [], horizon=62, refit_frames=10)
    progress.plan = plan
    save_fit(tmp_path / "f.h5", {"a": 1}, ["ks"], {"ks": np.float64(1.0)}, progress)
    back = load_fit_progress(tmp_path / "f.h5", {"a": 1}, ["ks"])
    assert back.plan == plan and isinstance(back.plan[0], Stage)
    assert (back.horizon, back.refit_frames) == (62, 10)
    progress.plan = None  # a progress made by hand has none: the fit plans its stages itself
    save_fit(tmp_path / "g.h5", {"a": 1}, ["ks"], {"ks": np.float64(1.0)}, progress)
    assert load_fit_progress(tmp_path / "g.h5", {"a": 1}, ["ks"]).plan is None
