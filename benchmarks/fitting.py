"""Fitting benchmark: every fitting/ experiment (with and without noise, float32 and float64),
optimizers (L-BFGS vs Adam) and long-horizon strategies (direct, curriculum, shooting).

Run from the repository root:
    python benchmarks/fitting.py [--part experiments|comparisons|all] [--out benchmarks/results]
Writes fitting_<part>.csv and fitting_<part>.md (a markdown table) into the output folder.
Each configuration runs in a fresh process so float32 and float64 do not mix.
"""

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

WORKER = r"""
import dataclasses, json, sys, time
import jax
config = json.loads(sys.argv[1])
jax.config.update("jax_enable_x64", config["dtype"] == "float64")
import numpy as np
import jaxspring as js
experiment = js.load_experiment(config["experiment"]).replace(noise=config["noise"])
if config.get("steps"):
    experiment = experiment.replace(steps=config["steps"], save_every=config["save_every"])
obs = experiment.observations()
settings = experiment.settings
settings = dataclasses.replace(settings, **{k: config[k] for k in ("optimizer", "strategy", "iterations") if k in config})
start = time.perf_counter()
result = js.fit(experiment.scene, obs, experiment.params, experiment.init, settings)
wall = time.perf_counter() - start
errors = result.relative_errors()
se = {n: float(np.max(result.identifiability.standard_error[n])) for n in result.names}
print(json.dumps({"iterations": result.iterations, "wall_s": wall, "final_loss": result.final_loss,
                  "stages": "+".join(f"{s.kind}({s.frames})" for s in result.stages),
                  "errors": errors, "standard_errors": se, "warnings": list(result.identifiability.warnings)}))
"""


def run(config):
    out = subprocess.run([sys.executable, "-c", WORKER, json.dumps(config)], capture_output=True, text=True, cwd=ROOT)
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def write_table(rows, path):
    """A markdown table: one row per configuration, the relative error of each parameter."""
    lines = [
        "| experiment | noise | dtype | optimizer / strategy | stages | iterations | wall [s] | relative errors |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        label = f"{row.get('optimizer') or 'lbfgs'} / {row.get('strategy') or 'auto'}"
        if row.get("steps"):
            label += f", {row['steps']} steps"
        name = Path(row["experiment"]).stem
        if row.get("error"):
            lines.append(f"| {name} | {row['noise']} | {row['dtype']} | {label} | failed: {row['error']} | | | |")
            continue
        errors = ", ".join(f"{k} {v:.1e}" for k, v in row["errors"].items())
        lines.append(
            f"| {name} | {float(row['noise']):.0%} | {row['dtype']} | {label} | {row['stages']} | "
            f"{row['iterations']} | {float(row['wall_s']):.1f} | {errors} |"
        )
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--part", choices=["experiments", "comparisons", "all"], default="all")
    args = parser.parse_args()
    rows = []
    experiments = ["mass_spring", "chain", "jelly", "cloth"]
    configs = []
    if args.part in ("experiments", "all"):
        configs += [
            dict(kind="experiment", experiment=f"fitting/{name}.toml", noise=noise, dtype=dtype)
            for dtype in ("float64", "float32")
            for name in experiments
            for noise in (0.0, 0.01)
        ]
    if args.part in ("comparisons", "all"):
        configs += [
            dict(
                kind="optimizer",
                experiment="fitting/chain.toml",
                noise=0.0,
                dtype="float64",
                optimizer="adam",
                iterations=400,
            ),
        ]
        clean = dict(kind="strategy", noise=0.0, dtype="float64")
        configs += [dict(clean, experiment="fitting/jelly.toml", strategy=s) for s in ("direct", "curriculum")]
        configs += [
            dict(clean, experiment="fitting/chain.toml", strategy=s, steps=5000, save_every=50)
            for s in ("direct", "curriculum", "shooting")
        ]
    for config in configs:
        t = time.perf_counter()
        outcome = run(config)
        print(f"{json.dumps(config)} -> {json.dumps(outcome)} ({time.perf_counter() - t:.0f} s)", flush=True)
        rows.append({**config, **outcome})
    folder = ROOT / args.out
    folder.mkdir(parents=True, exist_ok=True)
    fields = [
        "kind",
        "experiment",
        "noise",
        "dtype",
        "optimizer",
        "strategy",
        "steps",
        "iterations",
        "wall_s",
        "final_loss",
        "stages",
        "errors",
        "standard_errors",
        "warnings",
        "error",
    ]
    with open(folder / f"fitting_{args.part}.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: json.dumps(v) if isinstance(v, (dict, list)) else v for k, v in row.items()})
    write_table(rows, folder / f"fitting_{args.part}.md")


if __name__ == "__main__":
    main()
