"""Datasets: the helicopter dataset of the paper, a helicopter-like generator, real benchmarks.

* :func:`load_helicopter` reads the paper's normalised Stanford helicopter dataset (needs torch).
* :func:`helicopter_like` generates the documented stand-in (``docs/helicopter_benchmark.md``).
* :func:`load_benchmark`, :func:`windows` and :func:`benchmark_splits` read three real measured
  system-identification benchmarks (cascaded tanks, Silverbox, coupled electric drives).

All loaders work on the host in NumPy float64 and return :class:`ceemx.Trajectories`.
"""

from .benchmarks import (
    BENCHMARKS,
    BenchmarkRecord,
    WindowSplits,
    benchmark_splits,
    data_root,
    load_benchmark,
    windows,
)
from .heli_sim import helicopter_like, simulate_flights
from .helicopter import HelicopterData, load_helicopter

__all__ = [
    "BENCHMARKS",
    "BenchmarkRecord",
    "HelicopterData",
    "WindowSplits",
    "benchmark_splits",
    "data_root",
    "helicopter_like",
    "load_benchmark",
    "load_helicopter",
    "simulate_flights",
    "windows",
]
