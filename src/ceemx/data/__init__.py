"""Data: observed trajectories and where they live.

:class:`Trajectories` (y, u, mask; validated on construction; windows, first-order-hold inputs,
simulation of a system) in :mod:`~ceemx.data.trajectories`, its metadata (sample time, channel
names and units: :class:`DataInfo`) in :mod:`~ceemx.data.info`, records of different lengths and
NaN outputs in :mod:`~ceemx.data.records`, and the placement of the batch axis on
devices in :mod:`~ceemx.data.sharding`; records of the ``nonlinear-benchmarks`` package as
trajectories (:func:`from_nonlinear_benchmarks`, :mod:`~ceemx.data.interop`). Layer rule: may
import :mod:`ceemx.lib`, :mod:`ceemx.infra` and :mod:`ceemx.models`; the real datasets
(:mod:`ceemx.datasets`), inference, identification and evaluation build on it.
"""

from ceemx.data.info import DataInfo
from ceemx.data.interop import RecordInfo, from_nonlinear_benchmarks
from ceemx.data.trajectories import Trajectories, foh_inputs, rollout_one, simulate

__all__ = [
    "DataInfo",
    "RecordInfo",
    "Trajectories",
    "foh_inputs",
    "from_nonlinear_benchmarks",
    "rollout_one",
    "simulate",
]
