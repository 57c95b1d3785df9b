"""Spring groups: named runs of springs whose ks and kd differ ([[springs]] tables, lattice families).

Checked against the loop-based NumPy reference with per-spring values written out by hand,
across steppers, through files, by finite differences, and by a fit that recovers them.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy_reference import reference_rollout

import jaxspring as js
from jaxspring.cli import main

ROPE = {
    "name": "rope",
    "dt": 0.001,
    "physics": {"ks": {"stretch": 800.0, "bend": 6.0}, "kd": {"stretch": 0.8, "bend": 0.05}, "cd": 0.02},
    "particles": {"x": [[float(i), 0.0, 0.0] for i in range(6)], "pinned": [0], "drag": True},
    "springs": [
        {"name": "stretch", "pairs": [[i, i + 1] for i in range(5)]},
        {"name": "bend", "pairs": [[i, i + 2] for i in range(4)]},
    ],
}


@pytest.fixture(scope="module")
def rope():
    return js.scene_from_dict(ROPE)


def by_hand(stretch, bend):
    """Per-spring values in the rope's spring order: 5 stretch springs, then 4 bend springs."""
    return np.array([stretch] * 5 + [bend] * 4)


def reference(scene, ks, kd, steps):
    m = scene.model
    values = {"ks": ks, "kd": kd, "cd": float(scene.params.cd), "gravity": np.asarray(scene.params.gravity)}
    x, _ = reference_rollout(
        scene.state.x, scene.state.v, m.springs, m.rest_length, m.mass, m.pinned, m.drag, values, m.dt, steps, steps
    )
    return x[-1]


def test_rope_groups_follow_the_numpy_reference(rope):
    assert rope.model.spring_groups == (("stretch", 5), ("bend", 4))
    assert set(rope.params.to_dict()) == {"ks.stretch", "ks.bend", "kd.stretch", "kd.bend", "cd", "gravity"}
    got = js.rollout(rope.model, rope.params, rope.state, steps=300, save_every=300).x[-1]
    want = reference(rope, by_hand(800.0, 6.0), by_hand(0.8, 0.05), 300)
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-12)
    # a scalar applies to every group; a group's value can be changed by its dotted name
    bent = rope.with_values({"ks.bend": 60.0})
    assert float(bent.params.ks["bend"]) == 60.0 and float(bent.params.ks["stretch"]) == 800.0
    got = js.rollout(bent.model, bent.params, bent.state, steps=300, save_every=300).x[-1]
    np.testing.assert_allclose(
        np.asarray(got), reference(rope, by_hand(800.0, 60.0), by_hand(0.8, 0.05), 300), atol=1e-12
    )


def test_lattice_families_are_groups_on_every_stepper(scenes):
    cloth = scenes["cloth"]
    assert cloth.model.spring_groups == (("structural", 30 * 41 + 31 * 40), ("shear", 2 * 30 * 40))
    grouped = cloth.with_params(ks={"structural": 5000.0, "shear": 1500.0})
    per_spring = cloth.with_params(ks=np.array([5000.0] * 2470 + [1500.0] * 2400))
    want = js.rollout(per_spring.model.replace(lattice=None), per_spring.params, cloth.state, 60, 60).x[-1]
    for backend in ("jax", "auto", "native"):
        model = grouped.with_backend(backend).model
        got = js.rollout(model, grouped.params, cloth.state, 60, 60).x[-1]
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-11, err_msg=model.stepper.name)
    assert float(jnp.abs(want - js.rollout(cloth.model, cloth.params, cloth.state, 60, 60).x[-1]).max()) > 1e-6


def test_gradient_wrt_a_group_matches_finite_differences(rope):
    def loss(bend):
        params = rope.model.params_with(rope.params, {"ks.bend": bend})
        return jnp.sum(js.rollout(rope.model, params, rope.state, steps=200, save_every=200).x[-1, :, 1])

    grad = float(jax.grad(loss)(6.0))
    h = 1e-4
    fd = (float(loss(6.0 + h)) - float(loss(6.0 - h))) / (2 * h)
    assert grad == pytest.approx(fd, rel=1e-6) and abs(grad) > 1e-8


@pytest.mark.slow
def test_fit_recovers_each_groups_stiffness(rope):
    truth = {"ks": {"stretch": 800.0, "bend": 6.0}}
    obs = js.synthetic_observations(rope, truth, steps=400, save_every=20)
    assert obs.truth["ks.bend"] == 6.0
    result = js.fit(rope, obs, ["ks.stretch", "ks.bend"], init={"ks.stretch": 500.0, "ks.bend": 12.0}, iterations=60)
    assert abs(float(result.final["ks.stretch"]) / 800.0 - 1) < 1e-4
    assert abs(float(result.final["ks.bend"]) / 6.0 - 1) < 1e-3
    assert max(result.relative_errors().values()) < 1e-3


def test_files_keep_the_groups(tmp_path, rope):
    traj = js.rollout(rope.model, rope.params, rope.state, steps=20, save_every=10)
    js.save_trajectory(tmp_path / "rope.h5", rope, traj)
    loaded, _ = js.load_trajectory(tmp_path / "rope.h5")
    assert loaded.model.spring_groups == rope.model.spring_groups
    assert {k: float(v) for k, v in loaded.params.to_dict().items() if k != "gravity"} == {
        "ks.stretch": 800.0,
        "ks.bend": 6.0,
        "kd.stretch": 0.8,
        "kd.bend": 0.05,
        "cd": 0.02,
    }


def test_the_single_springs_table_still_loads(scenes):
    pair = scenes["mass_spring"]
    assert pair.model.spring_groups == () and jnp.ndim(pair.params.ks) == 0


@pytest.mark.parametrize(
    "change, words",
    [
        ({"physics": {**ROPE["physics"], "ks": {"stretch": 800.0}}}, ["ks", "no value for the group 'bend'"]),
        ({"physics": {**ROPE["physics"], "ks": {"stretch": 1.0, "bend": 1.0, "twist": 1.0}}}, ["ks.twist", "group"]),
        ({"springs": [{"name": "a", "pairs": [[0, 1]]}, {"name": "a", "pairs": [[1, 2]]}]}, ["share a name"]),
        ({"springs": [{"name": "a", "pairs": [[0, 1]]}, {"pairs": [[1, 2]]}]}, ["name", "missing"]),
        ({"physics": {**ROPE["physics"], "ks": {"stretch": -1.0, "bend": 1.0}}}, ["ks", ">= 0"]),
    ],
)
def test_bad_groups_are_one_line_errors(change, words):
    with pytest.raises(js.InputError) as info:
        js.scene_from_dict({**ROPE, **change})
    message = str(info.value)
    assert "\n" not in message and all(word in message for word in words), message


@pytest.mark.slow
def test_cli_set_names_a_group(tmp_path, capsys):
    assert (
        main(
            [
                "run",
                "cloth",
                "--steps",
                "20",
                "--save-every",
                "10",
                "--set",
                "ks.shear=2000",
                "--out",
                str(tmp_path / "c.h5"),
                "--quiet",
            ]
        )
        == 0
    )
    scene, _ = js.load_trajectory(tmp_path / "c.h5")
    assert float(scene.params.ks["shear"]) == 2000.0 and float(scene.params.ks["structural"]) == 5000.0
    assert main(["run", "cloth", "--steps", "20", "--save-every", "10", "--set", "ks.twist=1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ks.twist" in err[0] and "structural" in err[0]
