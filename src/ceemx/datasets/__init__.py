"""Datasets: the helicopter dataset of the paper, a helicopter-like generator, real benchmarks.

* :func:`load_helicopter` reads the paper's normalised Stanford helicopter dataset (needs torch).
* :func:`helicopter_like` generates the documented stand-in (``docs/helicopter_benchmark.md``).
* :func:`cascaded_tanks`, :func:`silverbox` and :func:`coupled_electric_drives` read three real
  measured system-identification benchmarks as :class:`BenchmarkDataset` objects (official
  records, ``n_init``, units, citation, published results); :func:`load_benchmark`,
  :func:`windows` and :func:`benchmark_splits` give their raw arrays and normalised windows. On
  first use the official files are downloaded into a user cache and their sha256 checked
  (:mod:`~ceemx.datasets.download`; ``CEEMX_DATA`` or ``root=`` name a folder of your own).

All loaders work on the host in NumPy float64 and return :class:`ceemx.Trajectories`.
"""

from ceemx.datasets.benchmarks import (
    BENCHMARKS,
    BenchmarkDataset,
    BenchmarkRecord,
    PublishedResult,
    WindowSplits,
    benchmark_dataset,
    benchmark_file,
    benchmark_splits,
    cascaded_tanks,
    coupled_electric_drives,
    data_root,
    load_benchmark,
    silverbox,
    windows,
)
from ceemx.datasets.download import DatasetUnavailable, cache_dir, fetch
from ceemx.datasets.heli_sim import helicopter_like, simulate_flights
from ceemx.datasets.helicopter import HelicopterData, load_helicopter

__all__ = [
    "BENCHMARKS",
    "BenchmarkDataset",
    "BenchmarkRecord",
    "DatasetUnavailable",
    "HelicopterData",
    "PublishedResult",
    "WindowSplits",
    "benchmark_dataset",
    "benchmark_file",
    "benchmark_splits",
    "cache_dir",
    "cascaded_tanks",
    "coupled_electric_drives",
    "data_root",
    "fetch",
    "helicopter_like",
    "load_benchmark",
    "load_helicopter",
    "silverbox",
    "simulate_flights",
    "windows",
]
