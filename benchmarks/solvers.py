"""Our least-squares and linear solvers side by side with optimistix and lineax.

Three comparisons, each on the same problem, the same start and the same machine, in
float64; times are medians of `--repeats` warm runs (compiled), plus the first (cold) run:

1. The whole-horizon Levenberg-Marquardt polish (`gauss_newton_polish`) against
   `optimistix.LevenbergMarquardt` (dense QR on the materialised Jacobian), on the chain
   over 1 s from values 30% off.
2. Multiple shooting with free segment states (`block_levenberg_marquardt`, linked blocks,
   the states eliminated along the chain of segments) against `optimistix.LevenbergMarquardt`
   on the same residuals flattened (the Jacobian is then one dense matrix): the chain over
   2 s, positions only, one continuity weight.
3. Backward Euler's inner solves (`jax.scipy.sparse.linalg` CG in Newton, GMRES for the
   tangent) against `lineax.CG` / `lineax.GMRES`: a 2 s chain rollout and its gradient.

    pip install -e ".[bench]"   # optimistix and lineax are not run-time dependencies
    python benchmarks/solvers.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import lineax as lx  # noqa: E402
import optimistix as optx  # noqa: E402

import jaxspring as js  # noqa: E402
from jaxspring.fit.block_lm import block_levenberg_marquardt  # noqa: E402
from jaxspring.fit.identifiability import gauss_newton_polish  # noqa: E402
from jaxspring.fit.objective import residual_function  # noqa: E402
from jaxspring.fit.settings import FitSettings  # noqa: E402
from jaxspring.fit.shooting import CONTINUITY_WEIGHTS, shooting_problem  # noqa: E402

integrators = importlib.import_module("jaxspring.sim.integrators")
ROOT = Path(__file__).parents[1]
TRUTH = {"ks": 1000.0, "kd": 5.0, "cd": 0.05}


def timed(run, repeats):
    """(first run's seconds, median of `repeats` more, the last result)."""
    clock = time.perf_counter()
    out = run()
    cold = time.perf_counter() - clock
    walls = []
    for _ in range(repeats):
        clock = time.perf_counter()
        out = run()
        walls.append(time.perf_counter() - clock)
    return cold, float(np.median(walls)), out


def worst(values):
    return max(abs(float(values[n]) / TRUTH[n] - 1) for n in TRUTH)


def whole_horizon(chain, repeats):
    obs = js.synthetic_observations(chain, TRUTH, 1000, 20)
    start = {n: 1.3 * v for n, v in TRUTH.items()}
    settings = FitSettings(polish_iterations=30, step_tolerance=1e-12, tolerance=1e-12)
    ours = timed(lambda: gauss_newton_polish(chain, obs, list(TRUTH), start, settings).final, repeats)
    flat, unravel, residuals = residual_function(chain, obs, list(TRUTH), start)
    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
    solve = jax.jit(lambda y: optx.least_squares(lambda z, _: residuals(z), solver, y, max_steps=60, throw=False).value)
    theirs = timed(
        lambda: {n: float(jnp.exp(v)) for n, v in unravel(jax.block_until_ready(solve(flat))).items()}, repeats
    )
    return [("whole-horizon LM, chain 1 s", "ours", ours), ("", "optimistix LM (QR)", theirs)]


def shooting(chain, repeats):
    obs = dataclasses.replace(js.synthetic_observations(chain, TRUTH, 2000, 20), states=None)
    start = {n: 1.3 * v for n, v in TRUTH.items()}
    problem = shooting_problem(chain, obs, list(TRUTH), start, 10, CONTINUITY_WEIGHTS[0])
    p0, unravel, s0, residual, data = problem.p0, problem.unravel, problem.s0, problem.residual, problem.data
    to_values = lambda p: {n: float(jnp.exp(v)) for n, v in unravel(jnp.asarray(p)).items()}  # noqa: E731
    ours = timed(
        lambda: to_values(block_levenberg_marquardt(residual, p0, s0, data, 50, 1e-12, linked=True).p), repeats
    )

    def flat_residuals(y, _):
        p, s = y
        r, ahead = jax.vmap(lambda s_b, d: residual(p, s_b, d))(s, data)
        return jnp.concatenate([r.reshape(-1), (ahead[:-1] - s[1:]).reshape(-1)])

    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
    solve = jax.jit(lambda y: optx.least_squares(flat_residuals, solver, y, max_steps=100, throw=False).value[0])
    theirs = timed(lambda: to_values(jax.block_until_ready(solve((p0, s0)))), repeats)
    return [
        (f"free shooting, chain 2 s ({s0.size} states)", "ours (block elimination)", ours),
        ("", "optimistix LM (QR, dense)", theirs),
    ]


def lineax_cg(matvec, b, tol, maxiter):
    operator = lx.FunctionLinearOperator(matvec, jax.eval_shape(lambda: b), tags=lx.positive_semidefinite_tag)
    solver = lx.CG(rtol=tol, atol=0.0, max_steps=maxiter)
    return lx.linear_solve(operator, b, solver, throw=False).value, None


def lineax_gmres(matvec, b, tol, restart, maxiter):
    operator = lx.FunctionLinearOperator(matvec, jax.eval_shape(lambda: b))
    solver = lx.GMRES(rtol=tol, atol=0.0, restart=restart, max_steps=restart * maxiter)
    return lx.linear_solve(operator, b, solver, throw=False).value, None


def backward_euler(chain, repeats):
    scene = chain.with_integrator(js.sim.BackwardEuler())
    model, state = scene.model, scene.state

    def loss(ks):
        params = model.params_with(scene.params, {"ks": ks})
        return jnp.sum(js.rollout(model, params, state, steps=2000, save_every=20).x[-1] ** 2)

    rows, ours = [], (integrators.cg, integrators.gmres)
    traced = []  # which inner solvers the traced step called

    def counted(solver, name):
        def call(*args, **kwargs):
            traced.append(name)
            return solver(*args, **kwargs)

        return call

    try:
        for label, cg, gmres in (
            ("ours (jax.scipy CG, GMRES)", ours[0], ours[1]),
            ("lineax CG, GMRES", lineax_cg, lineax_gmres),
        ):
            jax.clear_caches()  # the rollout's jitted step is traced again, with these solvers
            traced.clear()
            integrators.cg, integrators.gmres = counted(cg, "cg"), counted(gmres, "gmres")
            value_and_grad = jax.jit(jax.value_and_grad(loss))
            result = timed(lambda f=value_and_grad: [float(x) for x in jax.block_until_ready(f(1000.0))], repeats)
            assert {"cg", "gmres"} <= set(traced), f"{label}: the step did not trace its solvers ({traced})"
            rows.append(("backward Euler, chain 2 s, value and gradient" if not rows else "", label, result))
    finally:
        integrators.cg, integrators.gmres = ours
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    chain = js.load_scene(ROOT / "scenes" / "chain.toml")
    print("| problem | solver | first run | warm (median) | result |")
    print("|---|---|---|---|---|")
    for compare in (whole_horizon, shooting, backward_euler):
        rows = compare(chain, args.repeats)
        for problem, solver, (cold, warm, out) in rows:
            result = (
                f"largest error {worst(out):.1e}"
                if isinstance(out, dict)
                else f"loss {out[0]:.10g}, gradient {out[1]:.10g}"
            )
            print(f"| {problem} | {solver} | {cold:.1f} s | {warm:.1f} s | {result} |", flush=True)


if __name__ == "__main__":
    main()
