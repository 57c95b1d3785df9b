"""Speed against error: every integrator on every seed scene over a sweep of dt.

Run from the repository root:
    python benchmarks/accuracy.py            # = jaxspring bench accuracy --out-dir benchmarks/results
Writes accuracy.csv, accuracy.md (table + recommended settings) and accuracy.png
(log-log error against wall time per simulated second) into benchmarks/results.
"""

import sys
from pathlib import Path

from jaxspring.cli import main

if __name__ == "__main__":
    results = Path(__file__).resolve().parent / "results"
    sys.exit(main(["bench", "accuracy", "--out-dir", str(results), *sys.argv[1:]]))
