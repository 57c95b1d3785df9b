"""Levenberg-Marquardt (`fit.least_squares`) and the shooting stage's finish with it."""

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxspring as js
from jaxspring.fit.horizon import round_off_loss
from jaxspring.fit.least_squares import finish_segments, levenberg_marquardt, segment_least_squares
from jaxspring.fit.objective import segment_misfit_function, target_data

CHAIN_TRUTH = {"ks": 1000.0, "kd": 5.0, "cd": 0.05}


def test_levenberg_marquardt_fits_an_exponential_decay_exactly():
    """y = a exp(-b t) from exact samples, started 3x and 1/3 away: the answer is (a, b)."""
    t = np.linspace(0.0, 2.0, 25)
    a, b = 2.5, 1.7
    y = a * np.exp(-b * t)
    residual = lambda p: p[0] * np.exp(-p[1] * t) - y  # noqa: E731
    jacobian = lambda p: np.stack([np.exp(-p[1] * t), -p[0] * t * np.exp(-p[1] * t)], axis=1)  # noqa: E731
    solution = levenberg_marquardt(residual, jacobian, np.array([7.5, 0.6]), 50, 1e-12, 1e-12)
    np.testing.assert_allclose(solution.flat, [a, b], rtol=1e-10)
    costs = [loss for loss, _ in solution.history] + [solution.loss]
    assert np.all(np.diff(costs) < 0)  # downhill only


def test_levenberg_marquardt_follows_the_rosenbrock_valley():
    """Residuals (10 (y - x^2), 1 - x): a curved valley a plain Gauss-Newton step overshoots."""
    residual = lambda p: np.array([10 * (p[1] - p[0] ** 2), 1 - p[0]])  # noqa: E731
    jacobian = lambda p: np.array([[-20 * p[0], 10.0], [-1.0, 0.0]])  # noqa: E731
    solution = levenberg_marquardt(residual, jacobian, np.array([-1.2, 1.0]), 100, 1e-14, 1e-14)
    np.testing.assert_allclose(solution.flat, [1.0, 1.0], atol=1e-10)


def test_the_segments_jacobian_by_differences_matches_forward_mode(scenes):
    """The shooting stage's Jacobian (central differences through the native kernel) against
    jacfwd through the pure-JAX step, float64, on a chain with all three parameters."""
    scene = scenes["chain"]
    obs = js.synthetic_observations(scene, CHAIN_TRUTH, steps=200, save_every=10)
    names = ("ks", "kd", "cd")
    flat, unravel = ravel_pytree({n: jnp.log(jnp.asarray(0.8 * CHAIN_TRUTH[n])) for n in names})
    residual, jacobian, gradient = segment_least_squares(scene, obs, names, 5, unravel, flat.shape[0])
    data = target_data(obs)
    ours = np.asarray(jacobian(flat, data))
    forward = dataclasses.replace(scene, model=scene.model.forward_mode())
    misfit = segment_misfit_function(forward, obs, names, 5)
    exact = np.asarray(jax.jacfwd(lambda v: misfit(unravel(v), data).reshape(-1))(flat))
    assert ours.shape == exact.shape == (residual(flat, data).size, 3)
    scale = np.abs(exact).max(axis=0)
    assert np.all(scale > 0)
    np.testing.assert_allclose(ours / scale, exact / scale, atol=1e-5)
    r = np.asarray(residual(flat, data))
    np.testing.assert_allclose(np.asarray(gradient(flat, data)), exact.T @ r, rtol=1e-9)  # exact: reverse mode


def test_the_shooting_finish_leaves_noisy_segments_alone(scenes):
    """With 1% noise the segments' misfit is the noise's, far above round-off: their exact
    least-squares answer is no better than the optimiser's (the segments start from noisy
    states), so no step is taken (the float32 jelly in test_horizon.py is one that is finished)."""
    scene = scenes["chain"]
    names = ("ks", "kd", "cd")
    theta = {n: jnp.log(jnp.asarray([CHAIN_TRUTH[n]])) for n in names}
    settings = js.FitSettings()
    noisy = js.synthetic_observations(scene, CHAIN_TRUTH, steps=200, save_every=10, noise_relative=0.01)
    [left], _ = finish_segments(scene, [noisy], names, 5, theta, settings)
    assert left.history == [] and left.loss > 1e6 * round_off_loss(scene, noisy)
    np.testing.assert_array_equal(left.flat, ravel_pytree({n: theta[n][0] for n in names})[0])


def test_levenberg_marquardt_on_the_segments_finds_the_truth(scenes):
    """Differenced J^T J with the exact gradient, from 20% off on exact data: the truth."""
    scene = scenes["chain"]
    obs = js.synthetic_observations(scene, CHAIN_TRUTH, steps=200, save_every=10)
    names = ("ks", "kd", "cd")
    start, unravel = ravel_pytree({n: jnp.log(jnp.asarray(1.2 * CHAIN_TRUTH[n])) for n in names})
    residual, jacobian, gradient = segment_least_squares(scene, obs, names, 5, unravel, 3)
    data = target_data(obs)
    solution = levenberg_marquardt(
        lambda v: residual(v, data),
        lambda v: jacobian(v, data),
        np.asarray(start),
        30,
        1e-12,
        1e-12,
        gradient=lambda v: gradient(v, data),
    )
    for n, value in unravel(jnp.asarray(solution.flat)).items():
        assert abs(np.exp(float(value)) / CHAIN_TRUTH[n] - 1) < 1e-9, n


@pytest.mark.slow
def test_a_batch_finishes_each_member_on_its_own(scenes, monkeypatch):
    """Two targets in one fit_batch, exact and noisy, both let into the finish (as if stalled
    within round-off's reach) after three L-BFGS iterations: each ends its shooting stage
    where its own segments' gradient vanishes (the exact one at the truth), with histories
    of equal lengths, finite (the member that took fewer steps is padded with its answer)."""
    monkeypatch.setattr(importlib.import_module("jaxspring.fit.least_squares"), "FINISH_BELOW", np.inf)
    monkeypatch.setattr(importlib.import_module("jaxspring.fit.least_squares"), "stalled", lambda p: np.ones(2, bool))
    scene = scenes["chain"]
    names = ("ks", "kd", "cd")
    exact = js.synthetic_observations(scene, CHAIN_TRUTH, steps=200, save_every=10)
    noisy = js.synthetic_observations(scene, CHAIN_TRUTH, steps=200, save_every=10, noise_relative=0.01)
    start = {n: 1.5 * v for n, v in CHAIN_TRUTH.items()}
    results = js.fit_batch(
        scene,
        [exact, noisy],
        names,
        [start, start],
        js.FitSettings(strategy="shooting", segment_frames=5, iterations=3),
        identify=False,  # the standard errors are not looked at
    )
    _, unravel = ravel_pytree({n: jnp.zeros(()) for n in names})
    for result, obs in zip(results, (exact, noisy), strict=True):
        assert result.stages[0].kind == "shooting"
        end = int(np.argmax(result.stage_of_iteration == 1))  # the next stage's first row: the finish's answer
        assert end > 0 and len(result.loss_history) == result.stage_of_iteration.size + 1
        assert np.all(np.isfinite(result.loss_history))
        flat = np.array([np.log(result.value_history[n][end]) for n in sorted(names)])  # ravel order
        _, _, gradient = segment_least_squares(scene, obs, names, 5, unravel, 3)
        slope = np.asarray(gradient(jnp.asarray(flat), target_data(obs)))
        initial = np.asarray(gradient(jnp.log(jnp.array([start[n] for n in sorted(names)])), target_data(obs)))
        assert np.linalg.norm(slope) < 1e-4 * np.linalg.norm(initial)
        if obs is exact:
            for n, value in CHAIN_TRUTH.items():
                assert abs(result.value_history[n][end] / value - 1) < 1e-8, n
