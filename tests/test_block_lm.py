"""Block-arrow Levenberg-Marquardt against a dense least-squares solve written in the test."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxspring.fit import block_lm
from jaxspring.fit.block_lm import block_levenberg_marquardt

jax.config.update("jax_enable_x64", True)


def _linear_problem(blocks=4, shared=3, local=5, rows=30, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(blocks, rows, shared))
    c = rng.normal(size=(blocks, rows, local))
    y = rng.normal(size=(blocks, rows))
    return a, c, y


def _dense(a, c):
    """The stacked system's matrix: block b's rows see p (A_b) and their own s_b (C_b)."""
    blocks, rows, shared = a.shape
    local = c.shape[-1]
    dense = np.zeros((blocks * rows, shared + blocks * local))
    for b in range(blocks):
        dense[b * rows : (b + 1) * rows, :shared] = a[b]
        dense[b * rows : (b + 1) * rows, shared + b * local : shared + (b + 1) * local] = c[b]
    return dense


def test_linear_blocks_reach_the_dense_least_squares_answer_and_its_covariance():
    """r_b = A_b p + C_b s_b - y_b: the answer and the p-block of (J^T J)^-1 of the stacked
    (block-arrow) system, solved densely with NumPy."""
    a, c, y = _linear_problem()
    blocks, rows, shared = a.shape
    local = c.shape[-1]
    dense = _dense(a, c)
    answer = np.linalg.lstsq(dense, y.reshape(-1), rcond=None)[0]
    covariance = np.linalg.inv(dense.T @ dense)[:shared, :shared]

    def residual(p, s_b, d):
        return d["a"] @ p + d["c"] @ s_b - d["y"]

    data = {"a": jnp.asarray(a), "c": jnp.asarray(c), "y": jnp.asarray(y)}
    solution = block_levenberg_marquardt(residual, np.ones(shared), np.ones((blocks, local)), data, iterations=50)
    np.testing.assert_allclose(solution.p, answer[:shared], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(solution.s.reshape(-1), answer[shared:], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(solution.reduced), covariance, rtol=1e-8)
    expected = float(np.sum((dense @ answer - y.reshape(-1)) ** 2))
    np.testing.assert_allclose(solution.cost, expected, rtol=1e-10)
    assert solution.count == blocks * rows


def test_a_bound_holds_its_value_and_the_rest_reach_the_least_squares_answer_given_it():
    """p0 bounded above below its unconstrained answer: the answer has p0 on the bound and the
    other unknowns at the dense least-squares answer with p0 held there."""
    a, c, y = _linear_problem(seed=1)
    blocks, rows, shared = a.shape
    local = c.shape[-1]
    dense = _dense(a, c)
    free = np.linalg.lstsq(dense, y.reshape(-1), rcond=None)[0]
    bound = free[0] - 0.5
    rest = np.linalg.lstsq(dense[:, 1:], y.reshape(-1) - dense[:, 0] * bound, rcond=None)[0]

    def residual(p, s_b, d):
        return d["a"] @ p + d["c"] @ s_b - d["y"]

    data = {"a": jnp.asarray(a), "c": jnp.asarray(c), "y": jnp.asarray(y)}
    high = np.full(shared, np.inf)
    high[0] = bound
    solution = block_levenberg_marquardt(
        residual,
        np.full(shared, bound - 1),
        np.ones((blocks, local)),
        data,
        iterations=50,
        bounds=(np.full(shared, -np.inf), high),
    )
    assert solution.p[0] == pytest.approx(bound, abs=1e-12)
    np.testing.assert_allclose(solution.p[1:], rest[: shared - 1], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(solution.s.reshape(-1), rest[shared - 1 :], rtol=1e-7, atol=1e-9)


def test_a_nonlinear_problem_steps_only_downhill_to_its_exact_answer():
    """r_b = exp(p0 t) + p1 + s_b t^2 - data from p = (-0.7, 0.3), s = (0.1, -0.2, 0.4): noise-free,
    so the answer is exact; every accepted step lowers the cost."""
    t = jnp.linspace(0.0, 2.0, 25)
    truth_p, truth_s = np.array([-0.7, 0.3]), np.array([[0.1], [-0.2], [0.4]])

    def residual(p, s_b, d):
        return jnp.exp(p[0] * t) + p[1] + s_b[0] * t**2 - d

    data = jnp.stack([residual(jnp.asarray(truth_p), jnp.asarray(s), 0.0) for s in truth_s])
    solution = block_levenberg_marquardt(residual, np.array([0.2, -1.0]), np.zeros((3, 1)), data, iterations=60)
    np.testing.assert_allclose(solution.p, truth_p, atol=1e-8)
    np.testing.assert_allclose(solution.s, truth_s, atol=1e-8)
    costs = [cost for cost, _ in solution.history] + [solution.cost]
    assert all(later < earlier for earlier, later in zip(costs, costs[1:]))


@pytest.mark.parametrize("mask", [None, [True, False, True, True, False]], ids=["chain", "broken chain"])
def test_linked_blocks_reach_the_dense_least_squares_answer_and_its_covariance(mask):
    """Multiple shooting's structure: r_b = A_b p + C_b s_b - y_b and links G_b p + H_b s_b - s_{b+1}
    (b < B - 1, and only where `mask` keeps the link: the chain may break), so neighbouring
    blocks couple (block-tridiagonal); against the dense NumPy solve of the stacked system."""
    a, c, y = _linear_problem(blocks=5, seed=1)
    blocks, rows, shared = a.shape
    local = c.shape[-1]
    rng = np.random.default_rng(2)
    g, h = rng.normal(size=(blocks, local, shared)), rng.normal(size=(blocks, local, local))
    kept = [b for b in range(blocks - 1) if mask is None or mask[b]]
    links = len(kept) * local
    dense = np.zeros((blocks * rows + links, shared + blocks * local))
    target = np.concatenate([y.reshape(-1), np.zeros(links)])
    column = lambda b: slice(shared + b * local, shared + (b + 1) * local)  # noqa: E731
    for b in range(blocks):
        dense[b * rows : (b + 1) * rows, :shared] = a[b]
        dense[b * rows : (b + 1) * rows, column(b)] = c[b]
        if b in kept:
            i = kept.index(b)
            row = slice(blocks * rows + i * local, blocks * rows + (i + 1) * local)
            dense[row, :shared], dense[row, column(b)], dense[row, column(b + 1)] = g[b], h[b], -np.eye(local)
    answer = np.linalg.lstsq(dense, target, rcond=None)[0]
    covariance = np.linalg.inv(dense.T @ dense)[:shared, :shared]

    def residual(p, s_b, d):  # (the block's residuals, its link: the prediction of s_{b+1})
        return d["a"] @ p + d["c"] @ s_b - d["y"], d["g"] @ p + d["h"] @ s_b

    data = {k: jnp.asarray(v) for k, v in {"a": a, "c": c, "y": y, "g": g, "h": h}.items()}
    solution = block_levenberg_marquardt(
        residual, np.ones(shared), np.ones((blocks, local)), data, iterations=50, linked=True if mask is None else mask
    )
    np.testing.assert_allclose(solution.p, answer[:shared], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(solution.s.reshape(-1), answer[shared:], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(np.linalg.inv(solution.reduced), covariance, rtol=1e-8)
    np.testing.assert_allclose(solution.cost, float(np.sum((dense @ answer - target) ** 2)), rtol=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 0.05], ids=["exact", "noisy"])
def test_frozen_state_blocks_reach_the_same_answer_and_standard_errors(noise, monkeypatch):
    """Blocks whose states' Jacobian changes with p (r_b = exp(p0 t) (1 + s_b0 t^2 + s_b1 sin 3t)
    + p1 + s_b2 t + s_b3 cos 5t - y_b): with `frozen`, the blocks' systems are solved by
    conjugate gradients preconditioned by J_s^T J_s as it was taken, so the solve must end
    where the full Levenberg-Marquardt ends (to a small fraction of a standard error, the
    stopping rules' scale), with the same reduced matrix, both with the Jacobians taken again
    when the solves grow costly and with them never taken again (the start's J_s^T J_s
    preconditioning every solve, where a chord method would end elsewhere). With the
    iterations cut to one, the answer's reduced matrix comes from its full Jacobian."""
    t = jnp.linspace(0.0, 2.0, 25)
    truth_p = np.array([-0.7, 0.3])
    truth_s = np.random.default_rng(2).normal(scale=0.3, size=(4, 4))

    def residual(p, s_b, d):
        modes = 1.0 + s_b[0] * t**2 + s_b[1] * jnp.sin(3 * t)
        return jnp.exp(p[0] * t) * modes + p[1] + s_b[2] * t + s_b[3] * jnp.cos(5 * t) - d

    clean = np.stack([np.asarray(residual(jnp.asarray(truth_p), jnp.asarray(s), 0.0)) for s in truth_s])
    data = jnp.asarray(clean + noise * np.random.default_rng(3).normal(size=clean.shape))
    start = (np.array([-0.3, 0.0]), np.zeros_like(truth_s))
    full = block_levenberg_marquardt(residual, *start, data, iterations=200, tolerance=1e-14)
    kept = block_levenberg_marquardt(residual, *start, data, iterations=200, tolerance=1e-14, frozen=True)
    monkeypatch.setattr(block_lm, "CG_COST", 0.0)  # the Jacobians never taken again
    never = block_levenberg_marquardt(residual, *start, data, iterations=200, tolerance=1e-14, frozen=True)
    monkeypatch.setattr(block_lm, "CG_ITERATIONS", 1)  # every solve cut short: the answer's from its Jacobian
    short = block_levenberg_marquardt(residual, *start, data, iterations=20, frozen=True)
    there = block_levenberg_marquardt(residual, short.p, short.s, data, iterations=0)
    np.testing.assert_allclose(short.reduced, there.reduced, rtol=1e-10)
    for solution in (kept, never):
        costs = [cost for cost, _ in solution.history] + [solution.cost]
        assert all(later < earlier for earlier, later in zip(costs, costs[1:]))
        if noise == 0:
            np.testing.assert_allclose(solution.p, truth_p, atol=1e-8)
            np.testing.assert_allclose(solution.s, truth_s, atol=1e-8)
            continue
        dof = full.count - truth_p.size - truth_s.size
        se = np.sqrt(full.cost / dof * np.diag(np.linalg.inv(full.reduced)))
        assert np.all(np.abs(solution.p - full.p) <= 0.01 * se), (solution.p, full.p, se)
        np.testing.assert_allclose(solution.reduced, full.reduced, rtol=0.01)
