"""Benchmarks: speed against peers (`speed`, `peers`, `warp_kernels`) and speed against
error of every integrator (`accuracy`). `jaxspring bench speed|accuracy` runs them.

Example:
    >>> from jaxspring import bench
    >>> rows = bench.read_accuracy("benchmarks/results/accuracy.csv")
    >>> bench.recommend_settings(rows, tolerance=1e-3)
"""

from .accuracy import AccuracyRow
from .accuracy import plot as plot_accuracy
from .accuracy import read_csv as read_accuracy
from .accuracy import recommend as recommend_settings
from .accuracy import sweep as accuracy_sweep

__all__ = ["AccuracyRow", "accuracy_sweep", "plot_accuracy", "read_accuracy", "recommend_settings"]
