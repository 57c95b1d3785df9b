"""Success map of identification over long horizons: truths drawn, starts far off, with and
without noise, each case an experiment in fitting/cases/.

For each case, draws truths (log-uniform in the case's range below) and starts (each value
1/3 to 3 times its truth, log-uniform), simulates the case's target with them (positions
only, or positions and velocities of every particle: the `_velocities` cases), with 0 or 1%
noise, and fits it as the experiment file says (free segment states for positions-only
targets with contact or long horizons; "auto" with recorded velocities: shooting, then the
final stage over the horizon the misfit stays smooth over, then, where that answer leaves
more misfit than the positions' noise, position_shooting; the cloth: "auto", which fits
its whole smooth horizon directly). A draw succeeds when every value is within 2% of the
truth (no noise) or within 3 reported standard errors (noise; the standard errors are of
the log values, so the log of fitted / true is compared). Prints the success rate, the
median fit time and the worst draw per case.

    python benchmarks/success_map.py [--draws 10] [--cases chain_10s,small_jelly_1s] [--noise 0,0.01]
    python benchmarks/success_map.py --redraw   # table and figure from the CSV alone
    python benchmarks/success_map.py --cases jelly_1s_velocities --noise 0.01 --strategy position_shooting \
        --csv benchmarks/results/success_map_position_shooting.csv --figure docs/success_map_position_shooting.png

Every draw is kept in benchmarks/results/success_map.csv (a draw run again replaces its
row), so the map grows case by case; the table printed covers the draws just run, and the
figure (docs/success_map.png: each draw's worst error in units of its bound, and its fit
time) every draw in the CSV.

Cases (fitting/cases/NAME.toml; run one as an experiment with `jaxspring fit
fitting/cases/chain_10s.toml`): the chain over 10 s (500 frames, 50 segments), the same
without spring damping, `small_jelly_1s` (a 3 x 3 x 3 jelly with the jelly scene's
springs, ground and spin, dropped from 0.3 m, landing and bouncing over 1 s), the jelly
scene itself (7 x 6 x 5, spinning, several impacts) over 1, 2.5 and 4 s with recorded
velocities, and the cloth over 2 s. Positions-only, the jelly scene is not in the map: one
10-frame segment's Jacobian (1,260 state columns) costs ~35 s per Levenberg-Marquardt step
on 2 cores, beyond the 3-minute target.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxspring as js  # noqa: E402
from jaxspring.io.trajectory import atomic_path  # noqa: E402

ROOT = Path(__file__).parents[1]
CASES = ROOT / "fitting" / "cases"
RESULTS = ROOT / "benchmarks" / "results"
JELLY = {"ks": (150.0, 400.0), "kd": (0.02, 0.1)}
CHAIN = {"ks": (500.0, 2000.0), "kd": (2.0, 10.0), "cd": (0.02, 0.1)}
RANGES = {  # case -> {name: (low, high)}: the truths are drawn log-uniform in these
    "chain_10s": CHAIN,
    "undamped_chain_10s": {"ks": CHAIN["ks"], "cd": CHAIN["cd"]},
    "small_jelly_1s": JELLY,
    "jelly_1s_velocities": JELLY,
    "jelly_2.5s_velocities": JELLY,
    "jelly_4s_velocities": JELLY,
    "cloth_2s": {"ks": (2000.0, 10000.0), "kd": (0.2, 1.0), "cd": (0.001, 0.005)},
}


def draw(case: str, seed: int, noise: float):
    """(experiment, target, truth, start) of draw `seed` of `case` with relative `noise`."""
    experiment = js.load_experiment(CASES / f"{case}.toml")
    rng = np.random.default_rng(seed)
    ranges = RANGES[case]
    truth = {n: float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) for n, (lo, hi) in ranges.items()}
    start = {n: v * float(np.exp(rng.uniform(np.log(1 / 3), np.log(3)))) for n, v in truth.items()}
    target = experiment.replace(true_values=truth, noise=noise, seed=seed).observations()
    return experiment, target, truth, start


FIELDS = ("case", "noise", "seed", "success", "score", "seconds", "errors", "standard_errors", "stages")


def fit_draw(case: str, seed: int, noise: float, strategy: str | None = None) -> dict:
    """One draw fitted (with the experiment's strategy, or `strategy`): a CSV row (errors
    relative, standard errors of the log values)."""
    experiment, target, truth, start = draw(case, seed, noise)
    settings = experiment.settings if strategy is None else dataclasses.replace(experiment.settings, strategy=strategy)
    clock = time.perf_counter()
    result = js.fit(experiment.scene, target, experiment.params, start, settings)
    seconds = time.perf_counter() - clock
    error = {n: float(result.final[n]) / truth[n] - 1 for n in truth}
    se = {n: float(v) for n, v in result.identifiability.relative_standard_error.items()}
    # no noise: within 2%; noise: log error within 3 standard errors
    score = max(abs(e) / 0.02 if noise == 0 else abs(np.log1p(e)) / (3 * se[n]) for n, e in error.items())
    return {
        "case": case,
        "noise": noise,
        "seed": seed,
        "success": int(score <= 1.0),
        "score": score,
        "seconds": seconds,
        "errors": " ".join(f"{n}={e:.6g}" for n, e in error.items()),
        "standard_errors": " ".join(f"{n}={v:.6g}" for n, v in se.items()),
        "stages": " + ".join(f"{s.kind} {s.frames}" for s in result.stages),
    }


def read_rows(path: Path) -> list[dict]:
    """The CSV's draws (an absent file: none), numbers parsed."""
    if not path.exists():
        return []
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:
        row.update(noise=float(row["noise"]), seed=int(row["seed"]), success=int(row["success"]))
        row.update(score=float(row["score"]), seconds=float(row["seconds"]))
    return rows


def draw_order(row: dict) -> tuple:
    """Rows sort by case (in RANGES' order), noise, then seed."""
    return list(RANGES).index(row["case"]), row["noise"], row["seed"]


def write_rows(rows: list[dict], path: Path) -> None:
    rows = sorted(rows, key=draw_order)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def groups(rows: list[dict]) -> dict:
    """(case, noise) -> its draws, in the cases' order."""
    out: dict = {}
    for row in sorted(rows, key=draw_order):
        out.setdefault((row["case"], row["noise"]), []).append(row)
    return out


def table(rows: list[dict]) -> str:
    """Per case: successes, median and slowest fit, the worst draw, and the widest standard
    error reported (a success within 3 standard errors says little where they are wide)."""
    lines = [
        "| case | noise | success | median fit | slowest | worst | widest s.e. |",
        "|---|---|---|---|---|---|---|",
    ]
    for (case, noise), draws in groups(rows).items():
        seconds = [r["seconds"] for r in draws]
        wins = sum(r["success"] for r in draws)
        worst = max(r["score"] for r in draws)
        widest = max(float(v.split("=")[1]) for r in draws for v in r["standard_errors"].split())
        lines.append(
            f"| {case} | {noise:.0%} | {wins}/{len(draws)} | {np.median(seconds):.0f} s | {max(seconds):.0f} s"
            f" | {worst:.2g} of the bound | {widest:.2g} |"
        )
    return "\n".join(lines)


def figure(rows: list[dict], path: Path) -> None:
    """Each draw's worst error in units of its bound against its fit time, one row per case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = groups(rows)
    labels = [f"{case}, {noise:.0%} noise" for case, noise in cases]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 0.45 * len(cases) + 1.6), sharey=True)
    for row, draws in enumerate(cases.values()):
        wins = np.array([d["success"] for d in draws], bool)
        jitter = np.linspace(-0.2, 0.2, len(draws))
        scores = np.maximum([d["score"] for d in draws], 1e-14)
        seconds = [d["seconds"] for d in draws]
        for axis, values in ((left, scores), (right, seconds)):
            axis.scatter(np.asarray(values)[wins], (row + jitter)[wins], s=14, color="tab:blue")
            axis.scatter(np.asarray(values)[~wins], (row + jitter)[~wins], s=18, color="tab:red", marker="x")
        left.text(1e5, row, f"{wins.sum()}/{len(draws)}", va="center", fontsize=8)
    left.axvline(1.0, color="k", ls="--", lw=1)
    left.set(xscale="log", xlim=(1e-14, 1e7), xlabel="worst error / its bound (2%, or 3 standard errors)")
    left.set_yticks(range(len(cases)), labels, fontsize=8)
    left.invert_yaxis()
    right.axvline(180, color="k", ls="--", lw=1)
    right.set(xlabel="fit time [s], 2-core machine", xlim=(0, None))
    fig.suptitle("success map: drawn truths, starts 1/3-3x away (blue: success, red: miss)", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--first", type=int, default=0, help="the first draw's seed")
    parser.add_argument("--cases", default=",".join(RANGES), help="fitting/cases/ experiments, comma-separated")
    parser.add_argument("--noise", default="0,0.01")
    parser.add_argument("--verbose", action="store_true", help="print every draw")
    parser.add_argument("--csv", default=str(RESULTS / "success_map.csv"), help="draws kept here, merged by seed")
    parser.add_argument("--figure", default=str(ROOT / "docs" / "success_map.png"))
    parser.add_argument("--redraw", action="store_true", help="fit nothing: table and figure from the CSV")
    parser.add_argument("--strategy", help="fit with this strategy, not the experiments' (give its own --csv)")
    args = parser.parse_args()
    path = Path(args.csv)
    rows = read_rows(path)
    ran = []
    for case in [] if args.redraw else args.cases.split(","):
        if case not in RANGES:
            raise SystemExit(f"error: unknown case {case!r}; use one of {', '.join(RANGES)}")
        for noise in (float(x) for x in args.noise.split(",")):
            for seed in range(args.first, args.first + args.draws):
                row = fit_draw(case, seed, noise, args.strategy)
                ran.append(row)
                key = (case, noise, seed)
                rows = [r for r in rows if (r["case"], r["noise"], r["seed"]) != key] + [row]
                write_rows(rows, path)  # after every draw: an interrupted map keeps what it measured
                if args.verbose:
                    print(
                        f"  {case} {noise:.0%} seed {seed}: {row['errors']} (s.e. {row['standard_errors']}),"
                        f" {row['seconds']:.0f} s, {row['score']:.2g} of the bound; {row['stages']}",
                        flush=True,
                    )
    print(table(ran or rows))
    if rows:
        figure(rows, Path(args.figure))
        print(f"wrote {path} and {args.figure}")


if __name__ == "__main__":
    main()
