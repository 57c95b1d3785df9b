"""Levenberg-Marquardt for least squares with block-arrow structure.

The residuals come in blocks b = 1..B (one per recording, or per segment): block b
depends on the shared unknowns p (the parameters, P values) and on its own unknowns s_b
(its start state, L values), never on another block's. The normal matrix is then an
arrow: a P x P corner, B blocks L x L on the diagonal, and P x L couplings. Each step
eliminates the blocks (Schur complement), solves the P x P reduced system for p and
then every block's s_b on its own, so it costs B small solves, not one of size
P + B L. The same reduced matrix, inverted, is the covariance of p with every s_b
estimated too (not held), which the identifiability report uses.

Blocks' Jacobians are taken in forward mode, one block at a time (`lax.map`), so memory
holds one block's Jacobian (its residual count x (P + L)) at once.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


NOISE_FRACTION = 1e-4
"""A step lowering the cost by less than this fraction of the noise variance ends the solve."""


@dataclasses.dataclass
class BlockSolution:
    """p (P,), s (B, L); history of (cost before, p before) per accepted step; cost = sum r^2;
    reduced: the Schur-reduced normal matrix of p at the answer (P, P); count: residuals."""

    p: np.ndarray
    s: np.ndarray
    history: list
    cost: float
    reduced: np.ndarray
    count: int


def _normal_pieces(residual, p, s, data):
    """Per block: r, J_p^T J_p, J_p^T J_s, J_s^T J_s, J_p^T r, J_s^T r (one block at a time)."""
    size = p.shape[0]

    def block(args):
        s_b, data_b = args
        joint = jnp.concatenate([p, s_b])
        r = residual(p, s_b, data_b)
        jac = jax.jacfwd(lambda z: residual(z[:size], z[size:], data_b))(joint)
        jp, js = jac[:, :size], jac[:, size:]
        return r @ r, jp.T @ jp, jp.T @ js, js.T @ js, jp.T @ r, js.T @ r

    return jax.lax.map(block, (s, data))


def _costs(residual, p, s, data):
    return jax.vmap(lambda s_b, d: jnp.sum(residual(p, s_b, d) ** 2))(s, data)


def _solve(pieces, damping):
    """The damped arrow system's step (dp, ds) by the Schur complement; and the reduced matrix."""
    _, a, b, c, gp, gs = pieces
    corner = a.sum(axis=0)
    size, local = corner.shape[0], c.shape[-1]
    diag_c = jnp.diagonal(c, axis1=-2, axis2=-1)
    floor = 1e-12 * jnp.max(diag_c, axis=-1, keepdims=True) + 1e-300  # unknowns the data barely see
    c_damped = c + jnp.maximum(damping, 1e-12) * jnp.eye(local) * jnp.maximum(diag_c, floor)[..., None, :]
    c_inv_bt = jnp.linalg.solve(c_damped, jnp.swapaxes(b, -1, -2))  # (B, L, P)
    c_inv_gs = jnp.linalg.solve(c_damped, gs[..., None])[..., 0]  # (B, L)
    reduced = corner - jnp.einsum("bpl,blq->pq", b, c_inv_bt)
    damped = reduced + damping * jnp.diag(jnp.maximum(jnp.diag(corner), 1e-300))
    rhs = gp.sum(axis=0) - jnp.einsum("bpl,bl->p", b, c_inv_gs)
    dp = -jnp.linalg.lstsq(damped, rhs, rcond=1e-14)[0] if size else jnp.zeros(0)
    ds = -(c_inv_gs + jnp.einsum("blp,p->bl", c_inv_bt, dp))
    return dp, ds, reduced


def block_levenberg_marquardt(residual, p, s, data, iterations: int = 20, tolerance: float = 1e-12) -> BlockSolution:
    """Minimise sum_b |residual(p, s_b, data_b)|^2 from (p (P,), s (B, L)); data: a pytree of
    (B, ...) arrays. A step is taken only when the cost falls (never worse than given).

    Stops after `iterations` steps, when a step changes p by at most `tolerance` and the
    cost by at most that fraction, or when a step lowers the cost by less than
    `NOISE_FRACTION` of the noise variance the cost implies (cost / degrees of freedom):
    then p is within about sqrt(NOISE_FRACTION) standard errors of the minimum, and
    further steps (linear convergence when the residuals are noise, not zero) move it
    by amounts no one can measure."""
    pieces_fn = jax.jit(lambda p, s, d: _normal_pieces(residual, p, s, d))
    cost_fn = jax.jit(lambda p, s, d: _costs(residual, p, s, d).sum())
    solve = jax.jit(_solve)
    p, s = jnp.asarray(p), jnp.asarray(s)
    pieces = pieces_fn(p, s, data)
    cost = float(pieces[0].sum())
    count = int(jax.eval_shape(lambda: residual(p, s[0], jax.tree_util.tree_map(lambda x: x[0], data))).shape[0])
    freedom = max(count * s.shape[0] - p.size - s.size, 1)
    history, damping = [], 1e-3
    for _ in range(iterations):
        accepted = False
        for _ in range(12):
            dp, ds, _ = solve(pieces, damping)
            new_cost = float(cost_fn(p + dp, s + ds, data))
            if np.isfinite(new_cost) and new_cost < cost:
                accepted = True
                break
            damping *= 10.0
        if not accepted:
            break
        history.append((cost, np.asarray(p)))
        improvement = (cost - new_cost) / max(cost, 1e-300)
        below_noise = cost - new_cost <= NOISE_FRACTION * new_cost / freedom
        p, s, cost = p + dp, s + ds, new_cost
        damping = max(damping / 10.0, 1e-12)
        pieces = pieces_fn(p, s, data)
        if float(jnp.max(jnp.abs(dp), initial=0.0)) <= tolerance and improvement <= tolerance:
            break
        if improvement <= tolerance**2 or below_noise:
            break
    _, _, reduced = solve(pieces, 0.0)
    return BlockSolution(np.asarray(p), np.asarray(s), history, cost, np.asarray(reduced), count * s.shape[0])
