"""`jaxspring check` and `jaxspring bench accuracy`: outputs and their numbers."""

import csv

import numpy as np

from jaxspring.cli import main


def test_check_prints_every_integrators_bound(capsys):
    assert main(["check", "chain"]) == 0
    out = capsys.readouterr().out
    for name in ("semi_implicit_euler", "verlet", "rk4", "backward_euler"):
        assert name in out
    assert "omega_max 63.0" in out  # 2 sqrt(ks / m) for the chain's alternating mode: 2 sqrt(1000) = 63.2
    assert main(["check", "chain", "--dt", "0.05"]) == 1  # beyond 0.027 s
    assert "expect a blow-up" in capsys.readouterr().err
    assert main(["check", "chain", "--dt", "-1"]) == 2
    assert "dt" in capsys.readouterr().err


def test_bench_accuracy_quick(tmp_path, capsys):
    out = tmp_path / "bench"
    assert (
        main(["bench", "accuracy", "--quick", "--scenes", "mass_spring", "--repeats", "1", "--out-dir", str(out)]) == 0
    )
    with open(out / "accuracy.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 * 4  # integrators x dt values
    assert (out / "accuracy.png").stat().st_size > 10_000 and "Recommended" in (out / "accuracy.md").read_text()
    error = {(r["integrator"], float(r["dt"])): float(r["error"]) for r in rows}
    change = float(rows[0]["reference_change"])
    assert change < 1e-3 * min(error.values())  # the reference is converged far below every reported error
    for dt in (0.05, 0.02, 0.01, 0.005):
        assert error[("rk4", dt)] < error[("verlet", dt)] < error[("semi_implicit_euler", dt)]
    # halving dt halves the first-order error and quarters the second-order one
    assert np.isclose(error[("semi_implicit_euler", 0.01)] / error[("semi_implicit_euler", 0.005)], 2, rtol=0.1)
    assert np.isclose(error[("verlet", 0.01)] / error[("verlet", 0.005)], 4, rtol=0.1)
    assert main(["bench", "accuracy", "--scenes", "nope"]) == 2


def test_bench_speed_quick(tmp_path, capsys):
    out = tmp_path / "speed"
    args = ["bench", "speed", "--quick", "--peers", "jax_segment_sum,numpy", "--repeats", "1", "--out-dir", str(out)]
    assert main(args) == 0
    with open(out / "speed.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert {r["implementation"] for r in rows} >= {"jaxspring", "jax_segment_sum", "numpy"}
    assert {r["workload"] for r in rows} == {"chain", "cloth_31x41"}
    for r in rows:
        assert float(r["steps_per_second"]) > 0
        if not r["implementation"].startswith("jaxspring"):  # every peer computes the same motion
            assert float(r["max_difference"]) < 1e-3
        else:
            assert float(r["gradient_ratio"]) > 1 and float(r["memory_gradient_mib"]) > 0
    assert (out / "speed.png").stat().st_size > 10_000
    assert "x jax_segment_sum" in (out / "speed.md").read_text()
    assert main(["bench", "speed", "--peers", "cuda"]) == 2
    import jax

    assert jax.config.jax_enable_x64  # the float32 benchmark restored the suite's float64
