"""Datasets: the helicopter dataset of the paper, a helicopter-like generator, three real datasets.

* :func:`load_helicopter` reads the paper's normalised Stanford helicopter dataset (needs torch).
* :func:`helicopter_like` generates the documented stand-in (``docs/helicopter_benchmark.md``).
* :func:`friction_positioning` simulates a positioning stage under PID control whose friction
  (Stribeck + Coulomb + viscous) its user's physics lacks (:mod:`~ceemx.datasets.friction_sim`:
  the records, the true plant and the physics at a guess; ``docs/hybrid_models.md``).
* :func:`cascaded_tanks`, :func:`silverbox` and :func:`coupled_electric_drives` read three real
  measured nonlinear system-identification datasets as :class:`RealDataset` objects (official
  records, ``n_init``, units, citation, published results); :func:`load_records`,
  :func:`windows` and :func:`window_splits` give their raw arrays and normalised windows. On
  first use the official files are downloaded into a user cache and their sha256 checked
  (:mod:`~ceemx.datasets.download`; ``CEEMX_DATA`` or ``root=`` name a folder of your own).
* :data:`REGISTRY` holds one :class:`DatasetEntry` per real dataset: its official protocol, its
  gray-box model (:mod:`ceemx.systems.gray_box`) and the settings chosen by hand for fitting it.

All loaders work on the host in NumPy float64 and return :class:`ceemx.Trajectories`.
"""

from ceemx.datasets.download import DatasetUnavailable, cache_dir, data_file, data_root, fetch
from ceemx.datasets.friction_sim import friction_positioning
from ceemx.datasets.heli_sim import helicopter_like, simulate_flights
from ceemx.datasets.helicopter import HelicopterData, load_helicopter
from ceemx.datasets.records import (
    RawRecords,
    RealDataset,
    cascaded_tanks,
    coupled_electric_drives,
    load_records,
    real_dataset,
    silverbox,
)
from ceemx.datasets.registry import REGISTRY, DatasetEntry, PublishedResult
from ceemx.datasets.splits import WindowSplits, window_splits, windows

__all__ = [
    "REGISTRY",
    "DatasetEntry",
    "DatasetUnavailable",
    "HelicopterData",
    "PublishedResult",
    "RawRecords",
    "RealDataset",
    "WindowSplits",
    "cache_dir",
    "cascaded_tanks",
    "coupled_electric_drives",
    "data_file",
    "data_root",
    "fetch",
    "friction_positioning",
    "helicopter_like",
    "load_helicopter",
    "load_records",
    "real_dataset",
    "silverbox",
    "simulate_flights",
    "window_splits",
    "windows",
]
