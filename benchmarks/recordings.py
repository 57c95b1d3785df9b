"""Fit honest recordings and predict held-out ones: the numbers quoted in docs/fitting.md.

Makes rope recordings with benchmarks/rope_recordings.py (a finer rope, a different model),
fits the 12- and 34-particle chains with `jaxspring fit`, predicts the held-out recordings
with 95% bands (`jaxspring predict --bands 64`), and compares with the baseline "free markers
frozen at the start frame". Writes benchmarks/results/recordings.md.

    python benchmarks/recordings.py [--out DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import rope_recordings  # noqa: E402

from jaxspring.cli import main as cli  # noqa: E402


def run(argv: list[str]) -> tuple[float, str]:
    clock = time.perf_counter()
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = cli(argv)
    if code:
        raise SystemExit(f"jaxspring {' '.join(argv)} failed with {code}")
    return time.perf_counter() - clock, buffer.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="folder for the data and fits (default: a temporary folder)")
    parser.add_argument("--train", type=int, default=8, help="recordings to fit (default 8)")
    parser.add_argument("--held-out", type=int, default=4, help="recordings to predict (default 4)")
    parser.add_argument("--models", default="12,34", help="chain sizes to fit (default 12,34)")
    args = parser.parse_args()
    folder = Path(args.out or tempfile.mkdtemp(prefix="jaxspring-recordings-"))
    rope_recordings.make_rope_recordings(folder, train=args.train, held_out=args.held_out)
    held = sorted((folder / "held_out").glob("*.h5"))
    rows = []
    for n in [int(m) for m in args.models.split(",")]:
        fit_file = folder / f"rope{n}.fit.h5"
        fit_s, fitted = run(["fit", str(folder / f"rope{n}_experiment.toml"), "--out", str(fit_file), "--quiet"])
        predict_s, predicted = run(
            ["predict", str(fit_file), *map(str, held), "--out-dir", str(folder / f"pred{n}"), "--bands", "64"]
        )
        pooled = next(line for line in predicted.splitlines() if line.startswith("all ")).split()
        band = next(line for line in predicted.splitlines() if line.startswith("95% band"))
        # the pooled row: all, N, (pooled), per coordinate, distance, RMS, frozen per coordinate, frozen distance
        rows.append((n, fit_s, predict_s, float(pooled[3]), float(pooled[4]), float(pooled[-1]), band.split()[3]))
        print(fitted)
    lines = [
        f"# Honest recordings: fit {args.train}, predict {args.held_out} held out (benchmarks/recordings.py)",
        "",
        "Data: a 56-particle rope with stretch and bend springs, RK4 at dt = 1e-4 s, both ends moved along",
        "smooth random paths; 12 markers at 100 Hz, 500 frames, 1 mm noise, short drop-outs.",
        "",
        f"| model | fit {args.train} x 500 frames [s] | predict {args.held_out} [s] | held-out mean |error| per coordinate [mm] | mean distance [mm] | frozen at start, distance [mm] | 95% band coverage |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {n}-particle chain | {f:.0f} | {p:.1f} | {e:.2f} | {d:.2f} | {b:.2f} | {c} |"
        for n, f, p, e, d, b, c in rows
    ]
    out = Path(__file__).parent / "results" / f"recordings_{args.train}.md"
    out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
