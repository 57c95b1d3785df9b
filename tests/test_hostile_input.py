"""Inputs a user did not make with the same settings, and inputs that are plainly wrong.

Each test is a reproducer of a measured failure. Documented workflows must accept what they
are given; what they produce is checked independently (the file's own dtype, a rollout of the
cast state, the fit's loss history). Wrong inputs must be refused with exit code 2 and one line
naming the problem and the fix, with nothing written and every input untouched (or, in Python,
one `InputError`).
"""

import os
import shutil

import h5py
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import UNWRITABLE, _fitted_loss_fell, _jaxspring, _refused, needs_unwritable

import jaxspring as js
from jaxspring.cli import main
from jaxspring.io.scene import resolve_scene_path


@pytest.mark.slow
def test_fit_target_reads_a_float32_file_from_run(float32_recording):
    """The README's workflow: `run` (float32 by default), then `fit --target` (float64)."""
    result = _jaxspring(
        "fit", "--target", "rec.h5", "--params", "ks,kd", "--init", "ks=400,kd=2",
        "--iterations", "8", "--out", "cli.fit.h5", "--quiet", cwd=float32_recording,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    _fitted_loss_fell(float32_recording / "cli.fit.h5")


@pytest.mark.slow
def test_experiment_target_file_reads_a_float32_file(float32_recording):
    (float32_recording / "exp.toml").write_text(
        'scene = "chain"\n[target]\nfile = "rec.h5"\n[fit]\nparams = ["ks"]\ninit = { ks = 400.0 }\niterations = 8\n'
    )
    result = _jaxspring("fit", "exp.toml", "--out", "exp.fit.h5", "--quiet", cwd=float32_recording)
    assert result.returncode == 0, result.stderr
    _fitted_loss_fell(float32_recording / "exp.fit.h5")
    assert "file values" in result.stdout and " true " not in result.stdout  # the file's own values, not a truth
    experiment = js.load_experiment(float32_recording / "exp.toml")
    assert experiment.observations().truth_label == "file"
    declared = experiment.replace(true_values={"ks": 612.0}).observations()  # [target.true] with a file
    assert declared.truth_label == "true" and float(declared.truth["ks"]) == 612.0
    (float32_recording / "positions.toml").write_text(
        'scene = "chain"\n[target]\nfile = "rec.h5"\nvelocities = false\n[fit]\nparams = ["ks"]\n'
    )  # positions only, as a camera records them: the same positions, no states to start segments from
    positions = js.load_experiment(float32_recording / "positions.toml").observations()
    assert positions.states is None and experiment.observations().states is not None
    np.testing.assert_array_equal(positions.x, experiment.observations().x)


def test_observations_take_the_fits_precision(float32_recording):
    scene, trajectory = js.load_trajectory(float32_recording / "rec.h5")
    obs = js.observations_from_trajectory(scene, trajectory, scene.save_every)
    assert obs.x.dtype == np.float64 and obs.initial_state.x.dtype == jnp.float64
    assert obs.states.x.dtype == jnp.float64 and obs.states.v.dtype == jnp.float64
    np.testing.assert_array_equal(obs.x, np.asarray(trajectory.x, np.float64)[:, obs.particles])


def test_rollout_promotes_a_float32_state_on_a_float64_model(scenes):
    scene = scenes["chain"]
    low = js.State(x=scene.state.x.astype(jnp.float32) + 0.1, v=scene.state.v.astype(jnp.float32))
    cast = js.State(x=low.x.astype(jnp.float64), v=low.v.astype(jnp.float64))
    got = js.rollout(scene.model, scene.params, low, steps=50, save_every=10)
    want = js.rollout(scene.model, scene.params, cast, steps=50, save_every=10)
    assert got.x.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(got.x), np.asarray(want.x))
    end = js.sim.final_state(scene.model, scene.params, low, steps=50)
    np.testing.assert_array_equal(np.asarray(end.x), np.asarray(want.x[-1]))


# --- Refusals: exit code 2, one line naming the problem and the fix, nothing written or changed ---


def _non_utf8_variants(text: bytes):
    """The file with one byte 0x80-0xFF in a comment, in a string, at the start; and random bytes."""
    rng = np.random.default_rng(17)
    junk = rng.integers(0, 256, 400, dtype=np.uint8).tobytes()
    return {
        "comment": text.replace(b"\n", b"\n# \x80\n", 1),
        "string": text.replace(b'"', b'"\xe9', 1),
        "start": b"\xff" + text,
        "random": junk,
    }


@pytest.mark.parametrize("where", ["comment", "string", "start", "random"])
def test_scene_and_experiment_files_that_are_not_utf8(inputs, tmp_path, capsys, where):
    scene = tmp_path / "bad.toml"
    scene.write_bytes(_non_utf8_variants((inputs / "c.toml").read_bytes())[where])
    with pytest.raises(js.InputError, match="not UTF-8; save the file as UTF-8"):
        js.load_scene(scene)
    _refused(capsys, tmp_path, "run", scene, "--out", tmp_path / "bad.h5", naming=["bad.toml", "UTF-8"])

    experiment = tmp_path / "bad_exp.toml"
    experiment.write_bytes(_non_utf8_variants((inputs / "exp.toml").read_bytes())[where])
    with pytest.raises(js.InputError, match="not UTF-8"):
        js.load_experiment(experiment)
    _refused(capsys, tmp_path, "fit", experiment, naming=["bad_exp.toml", "UTF-8"])


def test_outputs_that_would_overwrite_an_input_are_refused(inputs, tmp_path, capsys):
    for name in ("c.toml", "R.h5"):
        shutil.copy(inputs / name, tmp_path / name)
    scene, recording = tmp_path / "c.toml", tmp_path / "R.h5"
    os.link(scene, tmp_path / "hard.h5")  # another name for the same file
    (tmp_path / "sub").mkdir()  # for sub/../R.h5, the same path spelt differently
    (tmp_path / "target.toml").write_text('scene = "c.toml"\n[target]\nfile = "R.h5"\n[fit]\nparams = ["ks"]\n')
    run = ["run", scene, "--steps", 20, "--save-every", 10]
    _refused(capsys, tmp_path, *run, "--out", scene, naming=["--out", "input"])
    _refused(capsys, tmp_path, *run, "--out", tmp_path / "hard.h5", naming=["--out", "input"])
    _refused(capsys, tmp_path, "render", recording, "--out", recording, naming=["--out"])
    fit = ["fit", "--target", recording, "--params", "ks", "--iterations", 1]
    _refused(capsys, tmp_path, *fit, "--out", recording, naming=["--out", "input"])
    _refused(capsys, tmp_path, *fit, "--out", tmp_path / "sub" / ".." / "R.h5", naming=["--out", "input"])
    _refused(capsys, tmp_path, "fit", tmp_path / "target.toml", "--out", recording, naming=["--out", "input"])


def test_fit_file_must_be_h5_so_the_plot_beside_it_is_another_file(inputs, capsys):
    _refused(capsys, inputs, "fit", inputs / "exp.toml", "--out", inputs / "res.png", naming=["--out", ".h5"])


@needs_unwritable
def test_outputs_in_a_folder_or_an_unwritable_place(inputs, capsys):
    recording = inputs / "R.h5"
    run = ["run", inputs / "c.toml", "--steps", 20, "--save-every", 10]
    _refused(capsys, inputs, *run, "--out", inputs, naming=["--out", "is a folder"])
    _refused(capsys, inputs, *run, "--out", UNWRITABLE / "c.h5", naming=["--out", "cannot write"])
    _refused(capsys, inputs, "render", recording, "--out", inputs, naming=["--out", "is a folder"])
    _refused(capsys, inputs, "render", recording, "--out", UNWRITABLE / "R.gif", naming=["--out", "cannot write"])
    _refused(capsys, inputs, "demo", "--out-dir", inputs / "c.toml", naming=["--out-dir", "is a file"])
    _refused(capsys, inputs, "demo", "--out-dir", UNWRITABLE / "demo", naming=["--out-dir", "cannot create"])


@pytest.mark.parametrize("count", [0, -5])
def test_render_needs_at_least_one_frame(inputs, capsys, count):
    _refused(
        capsys, inputs, "render", inputs / "R.h5", "--out", inputs / "R.gif", "--max-frames", count,
        naming=["--max-frames", f"got {count}"],
    )  # fmt: skip


def test_step_counts_beyond_the_limit_are_refused_up_front(inputs, capsys):
    huge = 2**32
    line = _refused(
        capsys, inputs, "run", inputs / "c.toml", "--steps", huge, "--save-every", huge, "--out", inputs / "o.h5",
        naming=["--steps", "1,000,000,000"],
    )  # fmt: skip
    assert f"{huge:,}" in line


@pytest.mark.parametrize("noise", ["nan", "inf", "-0.1"])
def test_fit_noise_must_be_finite_and_non_negative(inputs, capsys, noise):
    _refused(
        capsys, inputs, "fit", inputs / "exp.toml", "--noise", noise, "--out", inputs / "exp.fit.h5",
        naming=["--noise", "finite"],
    )  # fmt: skip


# --- Python API: InputError naming the argument ---


@pytest.mark.parametrize(
    "arguments, field",
    [({"steps": 2.5}, "steps"), ({"steps": "10"}, "steps"), ({"steps": 10, "save_every": True}, "save_every")],
)
def test_rollout_counts_are_integers(scenes, arguments, field):
    scene = scenes["chain"]
    with pytest.raises(js.InputError, match=f"^{field}: must be an integer"):
        js.rollout(scene.model, scene.params, scene.state, **arguments)


def test_rollout_of_zero_steps_is_frame_0(scenes):
    scene = scenes["chain"]
    traj = js.rollout(scene.model, scene.params, scene.state, steps=0, save_every=5)
    assert traj.x.shape == (1, *scene.state.x.shape) and traj.t.shape == (1,) and float(traj.t[0]) == 0.0
    np.testing.assert_array_equal(np.asarray(traj.x[0]), np.asarray(scene.state.x))
    np.testing.assert_array_equal(np.asarray(traj.v[0]), np.asarray(scene.state.v))
    end = js.sim.final_state(scene.model, scene.params, scene.state, steps=0)
    np.testing.assert_array_equal(np.asarray(end.x), np.asarray(scene.state.x))


def test_scene_changes_that_are_not_numbers(scenes):
    scene = scenes["chain"]
    with pytest.raises(js.InputError, match="^dt: must be a number, got 'abc'"):
        scene.with_dt("abc")
    with pytest.raises(js.InputError, match="^ks: must be a number or an array of numbers, got 'abc'"):
        scene.with_params(ks="abc")
    springs = scene.model.spring_count
    with pytest.raises(js.InputError, match=rf"^ks: has shape \({springs}, 1\); give a scalar or one value per spring"):
        scene.with_params(ks=np.full((springs, 1), 1000.0))


def _mutated(source, folder, name, mutate):
    """A copy of the trajectory file `source` changed by `mutate(h5py.File)`."""
    path = folder / f"{name}.h5"
    shutil.copy(source, path)
    with h5py.File(path, "r+") as f:
        mutate(f)
    return path


def _replace(dataset, data):
    def mutate(f):
        if dataset in f:
            del f[dataset]
        f.create_dataset(dataset, data=data)

    return mutate


MALFORMED = {
    "zero frames": (_replace("trajectory/x", np.zeros((0, 20, 3))), "no frames"),
    "nan t": (lambda f: f["trajectory/t"].__setitem__(3, np.nan), "not finite"),
    "inf t": (lambda f: f["trajectory/t"].__setitem__(3, np.inf), "not finite"),
    "array dt": (lambda f: f.attrs.__setitem__("dt", np.ones(3)), "malformed"),
    "group as t": (lambda f: (f.__delitem__("trajectory/t"), f.create_group("trajectory/t")), "malformed"),
    "decreasing t": (_replace("trajectory/t", np.linspace(1.0, 0.0, 21)), "strictly increasing"),
    "zero t": (_replace("trajectory/t", np.zeros(21)), "strictly increasing"),
    "rest length": (_replace("topology/rest_length", np.ones(3)), "rest_length"),
    "mass (N, 1)": (_replace("topology/mass", np.ones((20, 1))), "topology/mass"),
    "faces": (_replace("topology/faces", np.array([[0, 1, 99]], dtype=np.int32)), "face index"),
    "lattice": (lambda f: f["topology"].attrs.__setitem__("lattice_shape", np.array([7])), "lattice_shape"),
    "bytes ks": (_replace("params/ks", np.bytes_(b"stiff")), "not numeric"),
    "group as dataset": (lambda f: (f.__delitem__("topology"), f.create_dataset("topology", data=1.0)), "malformed"),
    "string dt": (lambda f: f.attrs.__setitem__("dt", "fast"), "malformed"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_trajectory_files_are_refused_in_one_line(float32_recording, tmp_path, capsys, case):
    mutate, word = MALFORMED[case]
    path = _mutated(float32_recording / "rec.h5", tmp_path, "bad", mutate)
    _refused(capsys, tmp_path, "render", path, "--out", tmp_path / "bad.png", naming=(word,))
    if case in ("lattice", "mass (N, 1)", "zero frames"):  # measured: these crashed `fit`
        _refused(
            capsys, tmp_path, "fit", "--target", path, "--params", "ks", "--out", tmp_path / "f.h5", naming=(word,)
        )


def test_frames_with_nan_positions_are_not_drawn(float32_recording, tmp_path, capsys):
    """Measured: a file with NaN positions rendered blank axes with exit 0."""
    bad = tmp_path / "bad.h5"
    shutil.copy(float32_recording / "rec.h5", bad)
    with h5py.File(bad, "r+") as f:
        f["trajectory/x"][5:, 3] = np.nan
    for out, extra in [("x.png", ()), ("x.gif", ()), ("y.png", ("--frame", "-1"))]:
        _refused(capsys, tmp_path, "render", bad, "--out", tmp_path / out, *extra, naming=("NaN or infinite",))
    assert main(["render", str(bad), "--out", str(tmp_path / "early.png"), "--frame", "4"]) == 0
    assert (tmp_path / "early.png").stat().st_size > 1000


@pytest.mark.parametrize(
    "change, message",
    [
        ({"ks": -5000.0}, "ks: must be >= 0"),
        ({"ks": float("nan")}, "ks: contains NaN"),
        ({"kg": 5.0}, "kg: the scene has no ground term"),
        ({"ks": np.full((19, 1), 1e3)}, r"ks: has shape \(19, 1\)"),
        ({"ks": "abc"}, "ks: must be a number"),
    ],
)
def test_rollout_checks_params_made_with_replace(scenes, change, message):
    """Measured: `params.replace(...)` (the README's pattern) reached the rollout unchecked: NaN
    trajectories, an ignored kg, a raw broadcasting error. Known values are checked; traced
    ones (jit, vmap, grad) are not, and gradients still flow."""
    scene = scenes["chain"]
    with pytest.raises(js.InputError, match=message):
        js.rollout(scene.model, scene.params.replace(**change), scene.state, steps=10)
    with pytest.raises(js.InputError, match=message):
        js.sim.final_state(scene.model, scene.params.replace(**change), scene.state, steps=10)


def test_a_state_of_the_wrong_shape_is_named(scenes):
    scene = scenes["chain"]
    wrong = js.State(x=jnp.zeros((3, 21)), v=jnp.zeros((3, 21)))
    with pytest.raises(js.InputError, match=r"state.x: has shape \(3, 21\) but the model has 20 particles"):
        js.rollout(scene.model, scene.params, wrong, steps=10)


def test_a_per_spring_fit_from_a_scalar_scene_value(scenes):
    """The start value's shape decides what is fitted (README), also when the scene's ks is one number."""
    chain = js.load_scene("chain")
    obs = js.synthetic_observations(chain, {"ks": 1000.0}, 100, 10)
    result = js.fit(chain, obs, ["ks"], init={"ks": np.full(19, 900.0)}, iterations=3, identify=False)
    assert np.shape(result.final["ks"]) == (19,)
    with pytest.raises(js.InputError, match=r"ks: has shape \(7,\); give a scalar or one value per spring \(19\)"):
        js.fit(chain, obs, ["ks"], init={"ks": np.full(7, 900.0)}, iterations=1)


def test_a_lattice_spacing_that_underflows_is_refused(capsys, tmp_path):
    scene = tmp_path / "tiny.toml"
    scene.write_text(resolve_scene_path("chain").read_text().replace("spacing = 1.0", "spacing = 1e-320"))
    _refused(capsys, tmp_path, "run", scene, "--out", tmp_path / "t.h5", naming=("spacing", "coincide"))


TWO = 'name = "two"\ndt = 0.001\n[physics]\nks = 100.0\nkd = 0.1\n[particles]\nx = [[0, 0, 0], [1, 0, 0]]\nmass = 1.0\n'


@pytest.mark.parametrize(
    "pinned, pairs, named",
    [
        ("[99999999999999999999]", "[[0, 1]]", "particles.pinned"),
        ("[-9223372036854775809]", "[[0, 1]]", "particles.pinned"),
        ("[9223372036854775807]", "[[0, 1]]", "particles.pinned"),
        ("[0]", "[[0, 99999999999999999999]]", "springs.pairs"),
        ("[0]", "[[0, 9223372036854775807]]", "springs"),
    ],
)
def test_spring_and_pinned_indices_beyond_int64(capsys, tmp_path, pinned, pairs, named):
    """Measured: OverflowError tracebacks (exit 1) for indices beyond int64."""
    scene = tmp_path / "two.toml"
    scene.write_text(TWO + f"pinned = {pinned}\n[springs]\npairs = {pairs}\n")
    _refused(capsys, tmp_path, "run", scene, "--out", tmp_path / "out.h5", "--quiet", naming=(named,))


@pytest.mark.parametrize(
    "springs, message",
    [
        ([[0, 2**70]], "particle index 1180591620717411303424 out of range 0..1"),
        ([[0, 2**63]], "particle index 9223372036854775808 out of range 0..1"),
        (np.array([[0, 2**63]], dtype=np.uint64), "particle index 9223372036854775808 out of range"),
        ([[0.5, 1]], "holds float 0.5, not a particle index"),
        ([[True, 1]], "holds bool True"),
        ([[0, 1, 1]], "has 3 indices, not rows of 2"),
    ],
)
def test_api_spring_indices_are_checked_whatever_their_type(springs, message):
    with pytest.raises(js.InputError, match=message):
        js.sim.make_model(springs=springs, mass=[1.0, 1.0], rest_length=[1.0])
    with pytest.raises(js.InputError, match="pinned: particle index 18446744073709551616 out of range"):
        js.sim.make_model(springs=[[0, 1]], mass=[1.0, 1.0], rest_length=[1.0], pinned=[2**64])


def test_wording_of_refusals_names_the_real_field_and_reason(inputs, capsys, tmp_path):
    """Measured: non-regular files called "not found", a scene's own steps blamed on --steps, a
    huge lattice count called an index, float32 overflow called "NaN or infinity"."""
    chain = resolve_scene_path("chain").read_text()
    (tmp_path / "s.toml").write_text(chain.replace("steps = ", "steps = 100000000000000000000000 #", 1))
    _refused(capsys, tmp_path, "run", tmp_path / "s.toml", "--out", tmp_path / "q.h5", naming=("chain: steps",))
    (tmp_path / "s.toml").write_text(chain.replace("steps = ", "steps = 1e23 #", 1))
    _refused(capsys, tmp_path, "run", tmp_path / "s.toml", "--out", tmp_path / "q.h5", naming=("steps", "integer"))
    (tmp_path / "l.toml").write_text(
        'name = "l"\ndt = 0.001\n[physics]\nks = 1.0\nkd = 0.0\n[lattice]\nshape = [99999999999999999999]\n'
    )
    _refused(capsys, tmp_path, "run", tmp_path / "l.toml", "--out", tmp_path / "q.h5", naming=("beyond any lattice",))
    _refused(capsys, tmp_path, "render", "/dev/zero", "--out", tmp_path / "x.png", naming=("not a regular file",))
    _refused(capsys, tmp_path, "fit", "/dev/zero", "--out", tmp_path / "f.h5", naming=("not a regular file",))
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    _refused(
        capsys,
        tmp_path,
        "fit",
        "--target",
        fifo,
        "--params",
        "ks",
        "--out",
        tmp_path / "f.h5",
        naming=("not a regular file",),
    )
    fifo.unlink()
    result = _jaxspring("run", "chain", "--set", "ks=1e308", "--out", "q.h5", cwd=tmp_path)  # float32: a fresh process
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "ks: 1e+308 overflows float32" in result.stderr and "--dtype float64" in result.stderr
    assert not (tmp_path / "q.h5").exists()
    _refused(
        capsys,
        inputs,
        "render",
        inputs / "R.h5",
        "--out",
        tmp_path / "r.gif",
        "--max-frames",
        "0",
        naming=("--max-frames",),
    )
    experiment = tmp_path / "e.toml"
    experiment.write_text((inputs / "exp.toml").read_text().replace("[target]", "[target]\nnoise = nan"))
    (tmp_path / "c.toml").write_text((inputs / "c.toml").read_text())
    _refused(capsys, tmp_path, "fit", experiment, "--out", tmp_path / "f.h5", naming=("noise",))
    scene = js.load_scene("chain")
    with pytest.raises(js.InputError, match="init.ks: 'abc' is not a number"):
        js.fit(scene, js.synthetic_observations(scene, {}, 20, 10), ["ks"], init={"ks": "abc"})
