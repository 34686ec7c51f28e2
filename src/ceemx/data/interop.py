"""Data from other packages: the ``nonlinear-benchmarks`` package's records.

:func:`from_nonlinear_benchmarks` takes what that package's loaders return — an
``Input_output_data`` (``u``, ``y``, ``sampling_time``, ``state_initialization_window_length``)
or a list or tuple of them — and gives :class:`~ceemx.data.trajectories.Trajectories`, so its
users can pass their data straight to :func:`ceemx.fit` and :func:`ceemx.benchmark_score`. The
package is not a dependency: any object with ``u`` and ``y`` arrays is accepted (duck typing).

Records of different lengths are padded to the longest at the end and the padding masked (the
mask is what :func:`ceemx.benchmark_score` and :func:`ceemx.fit` read), by
:meth:`ceemx.Trajectories.from_arrays` — the one implementation — which also takes NaN outputs as
missing samples and records the sample period in ``data.info``; ``with_info=True`` also returns
the sample period and the initialisation window ``n_init`` the package attached to its test
records (its ``state_initialization_window_length``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from ceemx.data.trajectories import Trajectories

__all__ = ["RecordInfo", "from_nonlinear_benchmarks"]


class RecordInfo(NamedTuple):
    """What the records say besides the signals (``None`` where none of them says it).

    Attributes:
        dt: the sample period (``sampling_time``), the same for every record.
        n_init: the initialisation window (``state_initialization_window_length``) for
            :func:`ceemx.benchmark_score`, the same for every record.
        names: each record's ``name`` (``None`` where it has none).
        lengths: each record's number of samples.
    """

    dt: float | None
    n_init: int | None
    names: tuple[str | None, ...]
    lengths: tuple[int, ...]


def _common(values: list, what: str):
    given = [v for v in values if v is not None]
    if not given:
        return None
    if any(not np.isclose(float(v), float(given[0]), rtol=1e-12, atol=0) for v in given):
        raise ValueError(f"the records disagree on `{what}`: {given}.")
    return given[0]


def from_nonlinear_benchmarks(
    data: Any | Sequence[Any], *, with_info: bool = False
) -> Trajectories | tuple[Trajectories, RecordInfo]:
    """Trajectories from ``nonlinear-benchmarks`` records (``Input_output_data``), one or several.

    Args:
        data: one record — any object with ``u`` and ``y`` arrays of shape (N,) or (N, k), and
            optionally ``sampling_time``, ``state_initialization_window_length`` and ``name`` —
            or a list or tuple of them (e.g. ``train_val, test = nonlinear_benchmarks.CED()``
            gives tuples of two records).
        with_info: also return a :class:`RecordInfo` (sample period, ``n_init``, names).

    Returns:
        :class:`~ceemx.data.trajectories.Trajectories` (B records, padded to the longest and the
        padding masked; NaN outputs masked; the sample period in ``info.dt``), or
        ``(trajectories, info)`` with ``with_info``.

    Raises:
        TypeError: a record without ``u`` or ``y``.
        ValueError: ``u`` and ``y`` of different lengths, arrays of rank > 2, records with
            different numbers of inputs or outputs, a NaN input, or disagreeing
            ``sampling_time`` or ``state_initialization_window_length``.

    Example:
        >>> train, test = nonlinear_benchmarks.Cascaded_Tanks()  # doctest: +SKIP
        >>> test_data, info = ceemx.data.from_nonlinear_benchmarks(test, with_info=True)
        ... # doctest: +SKIP
        >>> ceemx.benchmark_score(model, test_data, info.n_init)  # doctest: +SKIP
    """
    records: list[Any] = list(data) if isinstance(data, list | tuple) else [data]
    if not records:
        raise ValueError("no records given.")
    for i, r in enumerate(records):
        if not (hasattr(r, "u") and hasattr(r, "y")):
            raise TypeError(
                f"record {i} ({type(r).__name__}) has no `u` and `y`: expected a "
                "nonlinear_benchmarks Input_output_data or an object with `u` and `y` arrays."
            )
    ys = [np.asarray(r.y, np.float64) for r in records]
    us = [np.asarray(r.u, np.float64) for r in records]
    dt = _common([getattr(r, "sampling_time", None) for r in records], "sampling_time")
    dt = None if dt is None else float(dt)
    out = Trajectories.from_arrays(ys, us, dt=dt)  # padded and masked (data.records)
    if not with_info:
        return out
    n_init = _common(
        [getattr(r, "state_initialization_window_length", None) for r in records],
        "state_initialization_window_length",
    )
    info = RecordInfo(
        dt,
        None if n_init is None else int(n_init),
        tuple(getattr(r, "name", None) for r in records),
        tuple(len(y) for y in ys),
    )
    return out, info
