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
holds one block's Jacobian (its residual count x (P + L)) at once. When L is large (hundreds
of state values: a jelly's start positions), that Jacobian dominates the cost; `frozen`
then takes it rarely and, at each step, only J_p (P tangents) and the products
J_s^T [r, J_p] (one reverse pass). Each block's system (J_s^T J_s + damping) x =
[J_s^T J_p, J_s^T r] is solved by conjugate gradients with J_s^T J_s applied as it is at the
step (a forward and a transposed pass of the linearised block per iteration),
preconditioned by the J_s^T J_s last taken: inexact Gauss-Newton steps with the exact
gradient (so the same answer), and at the answer the reduced matrix to `CG_TOLERANCE` (from
the full Jacobian should the iterations run out). The Jacobian is taken again once the
solves since it was taken have cost as much (`CG_COST`).

Linked blocks (multiple shooting: block b's simulated end predicts block b + 1's start):
`residual` returns (r_b, link_b), and the residuals also hold link_b - s_{b+1} for
b < B - 1, so neighbouring blocks
couple: the blocks' part of the normal matrix is block-tridiagonal, and each step
eliminates it by block Gaussian elimination along the chain (a forward and a backward
sweep, `lax.scan`), still two L x L solves per block.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

NOISE_FRACTION = 1e-4
"""A step lowering the cost by less than this fraction of the noise variance ends the solve, as
does a failed step when the undamped (Gauss-Newton) step is predicted to lower it by less:
no more damping is tried, since a shorter step cannot gain what the data could show."""
ROUND_OFF = 1e-26
"""A cost below this fraction of the first one is exact data fitted to round-off: the solve ends."""
CG_TOLERANCE = 1e-10
"""With `frozen` blocks, the conjugate-gradient solves at the answer (its reduced matrix) end
when every column's residual is below this fraction of its right-hand side."""
CG_STEP_TOLERANCE = 1e-3
"""... and those of a step at this fraction: an inexact Gauss-Newton step converges as fast
as this fraction makes it (the gradient is exact, so the answer is the same)."""
CG_ITERATIONS = 100
"""With `frozen` blocks, the most conjugate-gradient iterations a solve takes."""
CG_COST = 1.5
"""One conjugate-gradient iteration's cost per right-hand side, in forward tangents (a
forward and a transposed pass of the linearised block; measured on the jelly's segments).
Once a `frozen` solve's iterations since the Jacobians were taken have cost as much as
taking them again (P + L tangents), they are taken again at the next point: the kept
J_s^T J_s, far from the current one, preconditions poorly."""


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


def _links(linked, count):
    """Which blocks link to the next one, (B,) bool, from `linked` (False, True, or a (B,) mask)."""
    last = np.arange(count) < count - 1
    return last & (np.asarray(linked, dtype=bool) if np.ndim(linked) else bool(linked))


@functools.lru_cache(maxsize=2)  # one problem's stages; older problems let go
def _compiled(residual, linked: bool):
    """The solver's jitted pieces for one residual function (reused across calls, e.g. the
    stages of a continuation): normal pieces, total cost, the damped solve, and for unlinked
    blocks the light pieces and the iterative solves (`frozen`)."""
    pieces = jax.jit(lambda p, s, d, links: _normal_pieces(residual, p, s, d, links if linked else False))
    cost = jax.jit(lambda p, s, d, links: _costs(residual, p, s, d, links if linked else False).sum())
    light = None if linked else jax.jit(lambda p, s, d, c: _light_pieces(residual, p, s, d, c))
    iterative = None if linked else jax.jit(functools.partial(_iterative_solves, residual))
    return pieces, cost, jax.jit(_solve), light, iterative


def _normal_pieces(residual, p, s, data, linked=False):
    """Per block: cost, J_p^T J_p, J_p^T J_s, J_s^T J_s, J_p^T r, J_s^T r, and when `linked` (True,
    or a (B,) mask of the blocks that link on) the couplings to the next block: E_b =
    -J_ls^T (L, L), F_b = -J_lp^T (P, L) and the defect c_b = link_b - s_{b+1} (one block at
    a time; all zero where a block does not link)."""
    size = p.shape[0]
    following = jnp.concatenate([s[1:], s[-1:]])
    last = jnp.arange(s.shape[0]) < s.shape[0] - 1
    has_next = last & (linked if jnp.ndim(linked) else bool(linked))
    linked = bool(jnp.ndim(linked)) or bool(linked)

    def block(args):
        s_b, data_b, next_b, on = args
        joint = jnp.concatenate([p, s_b])

        def rows(z):
            if not linked:
                return residual(z[:size], z[size:], data_b)
            r, ahead = residual(z[:size], z[size:], data_b)
            return jnp.concatenate([r, jnp.where(on, ahead, 0.0)])

        r = rows(joint)
        jac = jax.jacfwd(rows)(joint)
        if linked:
            r = r.at[r.shape[0] - s_b.shape[0] :].add(-jnp.where(on, next_b, 0.0))
        jp, js = jac[:, :size], jac[:, size:]
        out = (r @ r, jp.T @ jp, jp.T @ js, js.T @ js, jp.T @ r, js.T @ r)
        if not linked:
            return out
        local = s_b.shape[0]
        lp, ls, c = jp[-local:], js[-local:], r[-local:]
        return out + (-ls.T, -lp.T, c)

    return jax.lax.map(block, (s, data, following, has_next))


def _light_pieces(residual, p, s, data, c):
    """`_normal_pieces` of unlinked blocks with each block's J_s^T J_s given (`c`, (B, L, L)):
    J_p in forward mode (P tangents) and J_s^T [J_p, r] by one reverse pass, per block."""
    size = p.shape[0]

    def block(args):
        s_b, data_b = args
        r, pullback = jax.vjp(lambda z: residual(p, z, data_b), s_b)
        jp = jax.jacfwd(lambda q: residual(q, s_b, data_b))(p)
        products = jax.vmap(lambda u: pullback(u)[0])(jnp.concatenate([jp.T, r[None]]))  # (P + 1, L)
        return r @ r, jp.T @ jp, products[:size], jp.T @ r, products[size]

    cost, a, b, gp, gs = jax.lax.map(block, (s, data))
    return cost, a, b, c, gp, gs


def _damped_scale(c):
    """Each block's damping scale: the diagonal of c (B, L, L), floored for unknowns the data
    barely see."""
    diag_c = jnp.diagonal(c, axis1=-2, axis2=-1)
    floor = 1e-12 * jnp.max(diag_c, axis=-1, keepdims=True) + 1e-300
    return jnp.maximum(diag_c, floor)


def _right_sides(b, gs):
    """The blocks' right-hand sides [J_s^T J_p, J_s^T r], (B, L, P + 1)."""
    return jnp.concatenate([jnp.swapaxes(b, -1, -2), gs[..., None]], axis=-1)


def _conjugate_gradients(apply, precondition, rhs, tolerance, most):
    """X (L, K) with apply(X) = rhs for a symmetric positive definite `apply`, every column at
    once, preconditioned, to `tolerance` of each column's size or for `most` iterations; and
    the iterations taken."""
    goal = tolerance**2 * jnp.sum(rhs**2, axis=0)

    def ratio(num, den):
        return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)

    def going(state):
        i, _, r, _, _ = state
        return (i < most) & jnp.any(jnp.sum(r**2, axis=0) > goal)

    def iteration(state):
        i, x, r, d, rz = state
        q = apply(d)
        alpha = ratio(rz, jnp.sum(d * q, axis=0))
        x, r = x + alpha * d, r - alpha * q
        z = precondition(r)
        rz_next = jnp.sum(r * z, axis=0)
        return i + 1, x, r, z + ratio(rz_next, rz) * d, rz_next

    z = precondition(rhs)
    start = (0, jnp.zeros_like(rhs), rhs, z, jnp.sum(rhs * z, axis=0))
    i, x, *_ = jax.lax.while_loop(going, iteration, start)
    return x, i


def _iterative_solves(residual, p, s, data, c, damping, rhs, tolerance, most):
    """Per unlinked block, (J_s^T J_s + damping D) X = rhs (B, L, K) with J_s at (p, s_b),
    applied by the linearised block and its transpose, by conjugate gradients preconditioned
    by the kept c (B, L, L) + damping D (D: c's diagonal); and the most iterations a block took."""
    scale = _damped_scale(c)
    damping = jnp.maximum(damping, 1e-12)

    def block(args):
        s_b, data_b, c_b, scale_b, rhs_b = args
        _, forward = jax.linearize(lambda z: residual(p, z, data_b), s_b)
        backward = jax.linear_transpose(forward, s_b)
        normal = jax.vmap(lambda v: backward(forward(v))[0], in_axes=1, out_axes=1)
        factor = jax.scipy.linalg.cho_factor(c_b + damping * jnp.diag(scale_b))
        return _conjugate_gradients(
            lambda v: normal(v) + damping * scale_b[:, None] * v,
            lambda r: jax.scipy.linalg.cho_solve(factor, r),
            rhs_b,
            tolerance,
            most,
        )

    solved, iterations = jax.lax.map(block, (s, data, c, scale, rhs))
    return solved, jnp.max(iterations)


def _costs(residual, p, s, data, linked=False):
    if not (jnp.ndim(linked) or linked):
        return jax.vmap(lambda s_b, d: jnp.sum(residual(p, s_b, d) ** 2))(s, data)
    r, ahead = jax.vmap(lambda s_b, d: residual(p, s_b, d))(s, data)
    on = linked[:-1] if jnp.ndim(linked) else True
    gaps = jnp.where(on, jnp.sum((ahead[:-1] - s[1:]) ** 2, axis=-1), 0.0)
    return jnp.sum(r**2, axis=-1).at[:-1].add(gaps)


def _chain_solve(c, e, rhs):
    """X with T X = rhs for the block-tridiagonal T (diagonal blocks c (B, L, L), T[b, b+1] =
    e[b], T[b+1, b] = e[b]^T; e[B-1] unused), rhs (B, L, K): block elimination forwards, then
    back substitution."""

    def forward(carry, args):
        d_prev, y_prev, e_prev = carry
        c_b, rhs_b, e_b = args
        w = jnp.linalg.solve(d_prev, jnp.concatenate([e_prev, y_prev], axis=-1))
        local = c_b.shape[-1]
        d_b = c_b - e_prev.T @ w[:, :local]
        y_b = rhs_b - e_prev.T @ w[:, local:]
        return (d_b, y_b, e_b), (d_b, y_b)

    local = c.shape[-1]
    eye = jnp.eye(local, dtype=c.dtype)
    start = (eye, jnp.zeros_like(rhs[0]), jnp.zeros_like(e[0]))  # a zero coupling before block 0
    _, (d, y) = jax.lax.scan(forward, start, (c, rhs, e))

    def backward(x_next, args):
        d_b, y_b, e_b = args
        x_b = jnp.linalg.solve(d_b, y_b - e_b @ x_next)
        return x_b, x_b

    e_last = e.at[-1].set(0.0)
    _, x = jax.lax.scan(backward, jnp.zeros_like(rhs[0]), (d, y, e_last), reverse=True)
    return x


def _solve(pieces, damping, links=None, low=None, high=None, solved=None):
    """The damped system's step (dp, ds) by the Schur complement; the reduced matrix; and the
    cost's fall the step would bring were the residuals linear.
    `links`: (B,) which blocks link to the next (linked blocks); `low`, `high`: (P,) how far p
    may move (a value that would pass its bound stops there, the others are solved again
    given it, and ds is the blocks' best answer to that dp); `solved`: the blocks' damped
    systems already solved for their right-hand sides (`_iterative_solves`)."""
    _, a, b, c, gp, gs = pieces[:6]
    if len(pieces) > 6:  # linked blocks: block b + 1 also sees the defect of block b's link
        e, f, defect = pieces[6:]
        local = c.shape[-1]
        c = c.at[1:].add(jnp.eye(local, dtype=c.dtype) * links[:-1, None, None])
        b = b.at[1:].add(f[:-1])
        gs = gs.at[1:].add(-defect[:-1])
    corner = a.sum(axis=0)
    size, local = corner.shape[0], c.shape[-1]
    c_damped = c + jnp.maximum(damping, 1e-12) * jnp.eye(local) * _damped_scale(c)[..., None, :]
    if solved is None and len(pieces) > 6:
        solved = _chain_solve(c_damped, e, _right_sides(b, gs))
    elif solved is None:
        solved = jnp.linalg.solve(c_damped, _right_sides(b, gs))
    c_inv_bt, c_inv_gs = solved[..., :size], solved[..., size]
    reduced = corner - jnp.einsum("bpl,blq->pq", b, c_inv_bt)
    damped = reduced + damping * jnp.diag(jnp.maximum(jnp.diag(corner), 1e-300))
    rhs = gp.sum(axis=0) - jnp.einsum("bpl,bl->p", b, c_inv_gs)
    dp = -jnp.linalg.lstsq(damped, rhs, rcond=1e-14)[0] if size else jnp.zeros(0)
    if low is not None:  # values at their bounds held there; the others solved again given them
        held = (dp <= low) | (dp >= high)
        fixed = jnp.where(held, jnp.clip(dp, low, high), 0.0)
        free = jnp.where(held[:, None] | held[None, :], 0.0, damped) + jnp.diag(held.astype(damped.dtype))
        dp = fixed - jnp.linalg.lstsq(free, jnp.where(held, 0.0, rhs + damped @ fixed), rcond=1e-14)[0]
    ds = -(c_inv_gs + jnp.einsum("blp,p->bl", c_inv_bt, dp))
    # the cost's fall the linearised residuals predict, |r|^2 - |r + J d|^2 = -g.d + damping d.D.d
    # (d solves (J^T J + damping D) d = -g)
    shrink = jnp.sum(dp**2 * jnp.maximum(jnp.diag(corner), 1e-300)) + jnp.sum(ds**2 * _damped_scale(c))
    predicted = -(gp.sum(axis=0) @ dp + jnp.sum(gs * ds)) + jnp.maximum(damping, 1e-12) * shrink
    return dp, ds, reduced, predicted


def block_levenberg_marquardt(
    residual,
    p,
    s,
    data,
    iterations: int = 20,
    tolerance: float = 1e-12,
    linked=False,
    bounds=None,
    frozen: bool = False,
) -> BlockSolution:
    """Minimise sum_b |residual(p, s_b, data_b)|^2 (`linked`: residual returns (r_b, link_b), and
    the cost adds sum_{b < B-1} |link_b - s_{b+1}|^2; a (B,) mask `linked` keeps only the
    links of the blocks it marks, so the chain may break) from (p (P,), s (B, L)); data: a
    pytree of (B, ...) arrays. A step is taken only when the cost falls (never worse than
    given).

    Stops after `iterations` steps, when a step changes p by at most `tolerance` and the
    cost by at most that fraction, when two steps in a row change p and s by at most
    `tolerance` (round-off), or when a step lowers the cost by less than
    `NOISE_FRACTION` of the noise variance the cost implies (cost / degrees of freedom):
    then p is within about sqrt(NOISE_FRACTION) standard errors of the minimum, and
    further steps (linear convergence when the residuals are noise, not zero) move it
    by amounts no one can measure; or when the cost has fallen below `ROUND_OFF` of its
    first value (exact data, fitted to round-off); without `bounds`, also when a step fails
    and the undamped step is predicted to lower the cost by less than `NOISE_FRACTION` of the
    noise variance. `bounds`: (low, high), each (P,), a box p
    stays in (a value reaching its bound is held there while the others move). `frozen`
    (unlinked blocks only): take the blocks' J_s^T J_s only to precondition solves by
    conjugate gradients (module docstring)."""
    p, s = jnp.asarray(p), jnp.asarray(s)
    links = _links(linked, s.shape[0])
    linked = bool(np.ndim(linked)) or bool(linked)
    if frozen and linked:
        raise ValueError("frozen blocks must be unlinked")
    pieces_of, cost_of, solve_of, light_of, iterative_of = _compiled(residual, linked)
    on = jnp.asarray(links)
    spent = [0.0]  # with `frozen`: the solves' cost since the Jacobians were taken, in their units
    capped = [False]  # with `frozen`: the last solve ran out of iterations
    per_iteration = CG_COST * (p.size + 1) / (p.size + s.shape[1])

    def pieces_fn(p, s, d, kept=None):
        if kept is None or spent[0] >= 1.0:
            spent[0] = 0.0
            return pieces_of(p, s, d, on)
        return light_of(p, s, d, kept)

    cost_fn = lambda p, s, d: cost_of(p, s, d, on)  # noqa: E731
    low, high = (None, None) if bounds is None else (jnp.asarray(b, dtype=p.dtype) for b in bounds)

    def solve(pieces, damping, p, s):
        solved = None
        if frozen:  # the blocks' systems as they are at (p, s), preconditioned by the kept ones
            rhs = _right_sides(pieces[2], pieces[5])
            tolerance = CG_STEP_TOLERANCE if damping else CG_TOLERANCE  # a step, or the answer
            solved, iterations = iterative_of(p, s, data, pieces[3], damping, rhs, tolerance, CG_ITERATIONS)
            spent[0] += int(iterations) * per_iteration
            capped[0] = int(iterations) >= CG_ITERATIONS
        bounded = () if low is None else (low - p, high - p)
        return solve_of(pieces, damping, on.astype(s.dtype), *bounded, solved=solved)

    pieces = pieces_fn(p, s, data)
    cost = initial_cost = float(pieces[0].sum())
    first = jax.eval_shape(lambda: residual(p, s[0], jax.tree_util.tree_map(lambda x: x[0], data)))
    count = int((first[0] if linked else first).shape[0])
    rows = count * s.shape[0] + int(links.sum()) * s.shape[1]  # with the links' rows
    freedom = max(rows - p.size - s.size, 1)
    history, damping, still = [], 1e-3, False
    for _ in range(iterations):
        accepted = False
        for attempt in range(12):
            dp, ds, _, predicted = solve(pieces, damping, p, s)
            new_cost = float(cost_fn(p + dp, s + ds, data))
            if np.isfinite(new_cost) and new_cost < cost:
                accepted = True
                break
            floor = NOISE_FRACTION * cost / freedom  # a measurable fall
            if attempt == 0 and low is None and predicted <= floor:  # (a damped step's fall is at most GN's)
                if solve(pieces, 0.0, p, s)[3] <= floor and not capped[0]:
                    break  # not even the Gauss-Newton step could lower the cost measurably
            damping *= 10.0
        if not accepted:
            break
        history.append((cost, np.asarray(p)))
        improvement = (cost - new_cost) / max(cost, 1e-300)
        below_noise = cost - new_cost <= NOISE_FRACTION * new_cost / freedom
        p, s, cost = p + dp, s + ds, new_cost
        damping = max(damping / 10.0, 1e-12)
        pieces = pieces_fn(p, s, data, kept=pieces[3] if frozen else None)
        step = max(float(jnp.max(jnp.abs(dp), initial=0.0)), float(jnp.max(jnp.abs(ds), initial=0.0)))
        still, was_still = step <= tolerance, still
        if (
            new_cost <= ROUND_OFF * initial_cost
            or (float(jnp.max(jnp.abs(dp), initial=0.0)) <= tolerance and improvement <= tolerance)
            or (still and was_still)
            or improvement <= tolerance**2
            or below_noise
        ):
            break
    _, _, reduced, _ = solve(pieces, 0.0, p, s)
    if capped[0]:  # the iterations ran out: the answer's reduced matrix from its full Jacobian
        reduced = solve_of(pieces_of(p, s, data, on), 0.0, on.astype(s.dtype))[2]
    return BlockSolution(np.asarray(p), np.asarray(s), history, cost, np.asarray(reduced), count * s.shape[0])
