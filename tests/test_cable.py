"""`js.cable_scene`: a cable threaded through recorded markers, checked by hand: markers on their
particles, rest chords equal to the median seen marker distances, the spline through the
reference frame's markers, masses by arc length, segment groups, and its TOML text read back."""

import importlib.util
import sys
import tomllib
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxspring as js
from jaxspring.cli import main


def arc_recordings(frames=20, markers=6, seed=0, noise=1e-3):
    """Markers on a circular arc of radius 0.5 m, 0.1 m apart, swaying; one marker lost for 3 frames."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(2):
        angle = 0.2 * np.arange(markers)[None, :] + 0.02 * np.sin(np.arange(frames) / 3 + k)[:, None]
        x = np.stack([0.5 * np.sin(angle), np.zeros_like(angle), 0.5 * (1 - np.cos(angle))], axis=-1)
        x = x + rng.normal(0.0, noise, x.shape) + 0.01 * k
        x[4:7, 2] = np.nan
        out.append(js.Recording(t=0.01 * np.arange(frames), x=x))
    return out


def test_markers_sit_on_their_particles_and_rest_chords_are_the_median_distances():
    recs = arc_recordings()
    cable = js.cable_scene(recs, driven=(0, 1, -2, -1), subdivide=3, mass=0.3, reference=(0, 0))
    x = np.array(cable.scene["particles"]["x"])
    # intervals (0, 1) and (4, 5) join two driven markers: no particles between them
    assert cable.markers == [0, 1, 4, 7, 10, 11]
    assert cable.driven == [0, 1, 10, 11]
    np.testing.assert_allclose(x[cable.markers], recs[0].x[0], atol=1e-12)  # the spline passes through them
    stretch = next(g for g in cable.scene["springs"] if g["name"] == "stretch")
    assert stretch["pairs"] == [[i, i + 1] for i in range(11)]
    rest = np.array(stretch["rest_length"])
    for k, (a, b) in enumerate(zip(cable.markers[:-1], cable.markers[1:])):
        chord = x[b] - x[a]
        median = np.nanmedian([np.linalg.norm(r.x[f, k + 1] - r.x[f, k]) for r in recs for f in range(20)])
        # each interval's rest lengths are its reference lengths scaled so its chord is the median
        scale = median / np.linalg.norm(chord)
        np.testing.assert_allclose(rest[a:b], scale * np.linalg.norm(np.diff(x[a : b + 1], axis=0), axis=-1))
    mass = np.array(cable.scene["particles"]["mass"])
    np.testing.assert_allclose(mass.sum(), 0.3)
    np.testing.assert_allclose(mass[0], rest[0] / 2 / rest.sum() * 0.3)  # half its one spring's share
    bend = next(g for g in cable.scene["springs"] if g["name"] == "bend")
    i, j = bend["pairs"][3]
    assert j == i + 2
    scale = np.mean(rest[i:j] / np.linalg.norm(np.diff(x[i : j + 1], axis=0), axis=-1))
    np.testing.assert_allclose(bend["rest_length"][3], scale * np.linalg.norm(x[j] - x[i]))


def test_the_spline_is_curved_like_the_arc_between_markers():
    """Between markers 0.1 m apart on a circle of radius 0.5 m, the centripetal Catmull-Rom points
    stay within 0.02 mm of it, 0.1 mm in the end intervals (a straight chord between them sags 2.5 mm)."""
    recs = arc_recordings(noise=0.0)
    cable = js.cable_scene(recs, driven=(0, -1), subdivide=4, reference=(0, 0))
    x = np.array(cable.scene["particles"]["x"])
    assert len(x) == 21
    off = np.abs(np.linalg.norm(x - [0.0, 0.0, 0.5], axis=-1) - 0.5)
    assert off.max() < 1e-4 and off[4:17].max() < 2e-5


def test_straight_rest_and_segment_groups():
    recs = arc_recordings()
    cable = js.cable_scene(recs, driven=(0, 1, 4, 5), subdivide=2, groups=2, rest="straight")
    x = np.array(cable.scene["particles"]["x"])
    np.testing.assert_allclose(x[:, 1:], 0.0)
    medians = [
        np.nanmedian(np.concatenate([np.linalg.norm(r.x[:, k + 1] - r.x[:, k], axis=-1) for r in recs]))
        for k in range(5)
    ]
    np.testing.assert_allclose(x[cable.markers[-1], 0], np.sum(medians))
    names = [g["name"] for g in cable.scene["springs"]]
    assert names == ["stretch_1", "stretch_2", "bend_1", "bend_2"]
    first, last = cable.markers[1], cable.markers[4]  # the free cable between the clamps
    for group in cable.scene["springs"]:
        middles = [sum(p) / 2 for p in group["pairs"]]
        half = (first + last) / 2
        assert all(m < half for m in middles) if group["name"].endswith("_1") else all(m >= half for m in middles)
    assert set(cable.scene["physics"]["ks"]) == set(names)


def test_the_toml_text_reads_back_as_the_same_scene(tmp_path):
    recs = arc_recordings()
    cable = js.cable_scene(recs, subdivide=2, groups=3, mass=0.2)
    path = tmp_path / "cable.toml"
    path.write_text(cable.toml())
    assert tomllib.loads(path.read_text())["springs"] == cable.scene["springs"]
    a, b = js.load_scene(path), js.scene_from_dict(cable.scene)
    np.testing.assert_array_equal(np.asarray(a.state.x), np.asarray(b.state.x))
    for field in ("springs", "rest_length", "mass", "drag"):
        np.testing.assert_array_equal(np.asarray(getattr(a.model, field)), np.asarray(getattr(b.model, field)))
    assert a.model.spring_groups == b.model.spring_groups
    for u, v in zip(jax.tree_util.tree_leaves(a.params), jax.tree_util.tree_leaves(b.params)):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))


def test_the_bending_option_replaces_bend_springs_by_triples_bent_like_the_arc(tmp_path):
    """On a circle of radius 0.5 m, particles h apart turn by about h / 0.5 at each: the rest |kappa|
    = 2 tan(theta / 2) of every triple is that of the rest shape, about h / 0.5, and the TOML text
    keeps the triples."""
    recs = arc_recordings(noise=0.0)
    cable = js.cable_scene(recs, driven=(0, -1), subdivide=4, bending=True, values={"kb": 0.02, "kbd": 3e-4})
    assert [g["name"] for g in cable.scene["springs"]] == ["stretch"]
    assert cable.scene["bending"]["triples"] == [[i - 1, i, i + 1] for i in range(1, 20)]
    assert cable.scene["physics"]["kb"] == 0.02 and cable.scene["physics"]["kbd"] == 3e-4
    scene = js.scene_from_dict(cable.scene)
    x = np.array(cable.scene["particles"]["x"])
    h = np.linalg.norm(np.diff(x, axis=0), axis=-1)
    e1, e2 = np.diff(x, axis=0)[:-1], np.diff(x, axis=0)[1:]
    turning = np.arccos(np.sum(e1 * e2, axis=1) / (h[:-1] * h[1:]))
    rest = np.asarray(scene.model.rest_curvature)
    np.testing.assert_allclose(rest, 2 * np.tan(turning / 2), rtol=1e-9)
    np.testing.assert_allclose(rest, (h[:-1] + h[1:]) / 2 / 0.5, rtol=0.05)  # curvature 1 / R times the step
    path = tmp_path / "cable.toml"
    path.write_text(cable.toml())
    again = js.load_scene(path)
    np.testing.assert_array_equal(np.asarray(again.model.bends), np.asarray(scene.model.bends))
    np.testing.assert_allclose(np.asarray(again.model.rest_curvature), np.asarray(scene.model.rest_curvature))
    assert float(again.params.kb) == 0.02 and float(again.params.kbd) == 3e-4


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"subdivide": 0}, "at least 1"),
        ({"rest": "bent"}, "rest"),
        ({"reference": (0, 99)}, "outside"),
    ],
)
def test_bad_cable_arguments_fail_in_one_line(kwargs, words):
    with pytest.raises(js.InputError, match=words):
        js.cable_scene(arc_recordings(), **kwargs)


ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_the_shipped_cable_experiment_fits_and_predicts_held_out_takes(tmp_path, monkeypatch, capsys):
    """fitting/cable: recordings of a different model (an elastic rod with twist), a scene with the
    bending term; `jaxspring fit` then `jaxspring predict` as docs/fitting.md runs them. Two
    iterations from the scene's values already predict the held-out takes 10x better than frozen
    markers."""
    experiment = js.load_experiment(ROOT / "fitting" / "cable" / "experiment.toml")
    assert "bending" in experiment.scene.model.terms and "kb" in experiment.params
    monkeypatch.chdir(tmp_path)
    assert main(["fit", str(ROOT / "fitting/cable/experiment.toml"), "--iterations", "2", "--strategy", "direct"]) == 0
    capsys.readouterr()
    held = sorted(str(p) for p in (ROOT / "fitting" / "cable" / "held_out").glob("*.h5"))
    assert main(["predict", "experiment.fit.h5", *held, "--out-dir", "pred"]) == 0
    pooled = next(line for line in capsys.readouterr().out.splitlines() if "(pooled)" in line)
    numbers = [
        float(w.strip(",")) for w in pooled.split()[3:]
    ]  # coordinate, distance, RMS, frozen coordinate, distance
    assert numbers[0] < 0.1 * numbers[3], pooled
    assert sorted(p.name for p in (tmp_path / "pred").glob("*.h5")) == [Path(p).name for p in held]


@pytest.mark.slow
def test_the_cable_benchmark_runs_at_a_small_size(tmp_path, monkeypatch):
    """benchmarks/cables.py end to end on 2 short takes: data from the rod model, the plain rope and
    the bending rope fitted in their own processes (10 iterations, no start search), both
    predicting the held-out take far better than the frozen floor, in one table. Its `main`
    runs in this process; the fits still run in their own."""
    monkeypatch.setattr(sys, "path", list(sys.path))  # main puts benchmarks/ on it
    spec = importlib.util.spec_from_file_location("cables_benchmark", ROOT / "benchmarks" / "cables.py")
    cables = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cables)
    out = tmp_path / "cables.md"
    argv = ["--data", str(tmp_path / "data"), "--out", str(out), "--variants", "rope,rope_bending"]
    argv += ["--train", "2", "--held-out", "1", "--frames", "60", "--iterations", "10", "--search-starts", "1"]
    cables.main(argv)
    rows = [line.split("|") for line in out.read_text().splitlines() if line.startswith("| ") and "[" not in line]
    errors = {r[1].strip(): float(r[7]) for r in rows}  # held-out mean abs. error per coordinate [mm]
    floor = errors.pop("floor: free markers frozen at the start frame")
    assert len(errors) == 2 and all(0 < e < 0.5 * floor for e in errors.values()), errors


def hanging_recordings(up: int, takes=2, frames=60, seed=0):
    """A 5-marker rope (jaxspring's own, y up) hanging between two swaying grippers 0.3 m apart, its axes
    turned so that `up` (1: y, 2: z) is up; 1 mm noise."""
    rope = {
        "name": "rope",
        "dt": 0.002,
        "physics": {"ks": 300.0, "kd": 0.5, "cd": 0.02},
        "particles": {"x": [[0.1 * i, 0.0, 0.0] for i in range(5)], "mass": 0.03, "drag": True},
        "springs": {"pairs": [[i, i + 1] for i in range(4)]},
    }
    scene = js.scene_from_dict(rope)
    rng = np.random.default_rng(seed)
    turn = np.eye(3) if up == 1 else np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # y up -> z up
    out = []
    for _ in range(takes):
        t = np.arange(frames) * 0.01
        ends = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])[None] + 0.03 * np.sin(
            2 * np.pi * rng.uniform(0.5, 1.0, (1, 2, 3)) * t[:, None, None]
        )
        drive = js.sim.Drive(particles=(0, 4), t=jax.numpy.asarray(t), x=jax.numpy.asarray(ends))
        # hung first: 0.5 s at rest between the grippers, then the recorded motion
        still = js.sim.Drive(particles=(0, 4), t=jax.numpy.asarray([0.0, 1.0]), x=jax.numpy.asarray(ends[[0, 0]]))
        hung = js.rollout(scene.model, scene.params, scene.state, steps=250, save_every=250, drive=still)
        start = js.State(x=hung.x[-1], v=hung.v[-1])
        traj = js.rollout(scene.model, scene.params, start, steps=(frames - 1) * 5, save_every=5, drive=drive)
        x = np.asarray(traj.x) + rng.normal(0.0, 1e-3, (frames, 5, 3))
        out.append(js.Recording(t=t + 1.0, x=x @ turn.T))
    return out


def test_gravity_is_read_from_the_sag_and_a_wrong_up_axis_is_refused(capsys):
    for up, down in ((1, [0.0, -9.81, 0.0]), (2, [0.0, 0.0, -9.81])):
        cable = js.cable_scene(hanging_recordings(up), driven=(0, -1))
        assert cable.scene["physics"]["gravity"] == down
        assert "inferred from how the markers sag" in capsys.readouterr().out
        scene = js.scene_from_dict(tomllib.loads(cable.toml()))
        np.testing.assert_allclose(np.asarray(scene.params.gravity), down)
    z_up = hanging_recordings(2)
    given = js.cable_scene(z_up, driven=(0, -1), gravity=(0, 0, -9.8))
    assert given.scene["physics"]["gravity"] == [0.0, 0.0, -9.8]
    with pytest.raises(js.InputError, match=r"is \d+ degrees from the direction the markers sag"):
        js.cable_scene(z_up, driven=(0, -1), gravity=(0, -9.81, 0))  # the project's y up, on z-up data
    line = np.linspace(0, 1, 5)[:, None] * np.array([1.0, 0, 0])  # five markers on a straight line
    taut = [js.Recording(t=r.t, x=np.broadcast_to(line, r.x.shape).copy()) for r in z_up]
    with pytest.raises(js.InputError, match="cannot be inferred"):
        js.cable_scene(taut, driven=(0, -1))
    with pytest.raises(js.InputError, match="three numbers"):
        js.cable_scene(z_up, driven=(0, -1), gravity=(0, -9.81))


@pytest.mark.slow
def test_the_same_motion_recorded_y_up_and_z_up_fits_the_same_values():
    fits = []
    for up in (1, 2):
        recs = hanging_recordings(up)
        cable = js.cable_scene(recs, driven=(0, -1), rest="straight")
        scene = js.scene_from_dict(cable.scene)
        target = js.recording_target(scene, recs, markers=cable.markers, driven=cable.driven, start=1)
        fits.append(js.fit(scene, target, ["ks.stretch", "kd.stretch", "cd"], strategy="direct", identify=False))
    for n in ("ks.stretch", "kd.stretch", "cd"):
        assert float(fits[0].final[n]) == pytest.approx(float(fits[1].final[n]), rel=1e-6), n
    assert fits[0].loss_history[-1] == pytest.approx(fits[1].loss_history[-1], rel=1e-9)
