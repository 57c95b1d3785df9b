"""Levenberg-Marquardt as a fit stage's optimiser (`optimizer = "auto"` on recordings, or "lm"):
its residuals are the stage's loss, its answer is the least-squares one found independently, it
stops by its own rules, and a fit interrupted inside it resumes to the same bits."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest
from test_recordings_fit import ROPE, make_recordings

import jaxspring as js
from jaxspring.fit.least_squares import least_squares_residual, levenberg_marquardt
from jaxspring.fit.objective import loss_function, stage_residual_function, target_data
from jaxspring.fit.settings import Stage

NAMES = ["ks.stretch", "kd.stretch", "cd"]
START = {"ks.stretch": 250.0, "kd.stretch": 0.6, "cd": 0.03}


@pytest.fixture(scope="module")
def problem():
    scene = js.scene_from_dict(ROPE)
    recs = make_recordings(scene, 2, 40, noise=1e-3)
    target = js.recording_target(scene, recs, driven=[0, 5], start=1)
    return scene, target


def test_the_residuals_squared_sum_to_the_stage_loss(problem):
    scene, target = problem
    stage = Stage("direct", target.frame_count - 1)
    residual = stage_residual_function(scene, target, NAMES, stage)
    loss = loss_function(scene, target, NAMES, stage)
    data = target_data(target)
    for values in (START, {"ks.stretch": 400.0, "kd.stretch": 1.0, "cd": 0.05}):
        theta = {n: jnp.log(values[n]) for n in NAMES}
        assert float(jnp.sum(residual(theta, data) ** 2)) == pytest.approx(float(loss(theta, data)), rel=1e-10)
    # a robust loss is not a sum of squares: no residual, the stage keeps L-BFGS
    huber = dataclasses.replace(target, loss="huber")
    assert stage_residual_function(scene, huber, NAMES, stage) is None
    theta = {n: jnp.zeros((1,)) for n in NAMES}
    assert least_squares_residual(scene, target, NAMES, stage, js.FitSettings(), theta) is not None
    assert least_squares_residual(scene, target, NAMES, stage, js.FitSettings(optimizer="lbfgs"), theta) is None


def test_the_lm_stage_ends_at_the_least_squares_answer_found_by_numpy(problem):
    scene, target = problem
    result = js.fit(scene, target, NAMES, START, strategy="direct", identify=False)
    assert result.stages[0].kind == "direct" and result.iterations < 30
    # independently: NumPy Levenberg-Marquardt with a central-difference Jacobian of the misfit
    stage = Stage("direct", target.frame_count - 1)
    residual = stage_residual_function(scene, target, NAMES, stage)
    data = target_data(target)

    def r(flat):
        return np.asarray(residual({n: jnp.asarray(v) for n, v in zip(NAMES, flat)}, data))

    def jac(flat, h=1e-6):
        return np.stack([(r(flat + h * e) - r(flat - h * e)) / (2 * h) for e in np.eye(len(flat))], axis=1)

    flat = np.log([START[n] for n in NAMES])
    answer = levenberg_marquardt(r, jac, flat, 100, 1e-10, 1e-12).flat
    report = js.identifiability(scene, target, NAMES, result.final)
    for n, v in zip(NAMES, answer):
        se = float(report.standard_error[n])
        # within a tenth of a standard error: closer than the data decide (LM_REMAINING)
        assert abs(float(result.final[n]) - np.exp(v)) <= 0.1 * se, (n, float(result.final[n]), np.exp(v), se)


def test_a_fit_interrupted_inside_the_lm_stage_resumes_to_the_same_bits(problem):
    scene, target = problem
    settings = js.FitSettings(strategy="direct")
    saved = []

    def keep(progress, stages):
        if progress.iteration == 2 and not saved:
            saved.append(dataclasses.replace(progress, theta=dict(progress.theta), loss=list(progress.loss)))
            saved[0].values = {n: list(v) for n, v in progress.values.items()}
            saved[0].stage_of_iteration = list(progress.stage_of_iteration)
            saved[0].optimizer_leaves = [np.array(a) for a in progress.optimizer_leaves]

    whole = js.fit_batch(scene, [target], NAMES, [START], settings, on_iteration=keep, identify=False)[0]
    assert saved and len(saved[0].optimizer_leaves) == 3  # damping, dof, remaining
    resumed = js.fit_batch(scene, [target], NAMES, [START], settings, progress=saved[0], identify=False)[0]
    for n in NAMES:
        assert np.array_equal(np.asarray(resumed.final[n]), np.asarray(whole.final[n])), n
    assert np.array_equal(resumed.loss_history, whole.loss_history)


def test_an_lm_step_moves_a_value_the_residuals_hardly_see_a_bounded_way():
    """A near-zero Jacobian column, damped in its own tiny scale, threw its log value to 5e9 (a
    value of exactly 0, refused as a start value thereafter) and the other value past its answer."""
    from jaxspring.fit.least_squares import LM_LARGEST_STEP, lm_step_function

    def residual(theta, data):  # a is fitted by the data; b barely matters and is coupled to a
        a, b = theta["a"], theta["b"]
        return jnp.stack([a - 1.0 + 1e-9 * b, 1e-9 * (a + b) - data])

    step, init = lm_step_function(residual, data_batched=False)
    theta = {"a": jnp.array([3.0]), "b": jnp.array([0.0])}
    new, _, cost = step(theta, init(theta), jnp.asarray(5.0))
    assert float(cost[0]) == pytest.approx(4.0 + 25.0)  # the loss before the step
    assert float(new["a"][0]) == pytest.approx(1.0, abs=1e-2)  # a Gauss-Newton step for a
    assert abs(float(new["b"][0])) <= LM_LARGEST_STEP
    assert float(jnp.sum(residual({n: v[0] for n, v in new.items()}, 5.0) ** 2)) == pytest.approx(25.0, rel=1e-6)
