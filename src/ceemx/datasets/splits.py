"""Normalised train/validation/test windows of a real dataset's records.

:func:`windows` cuts one record into windows; :func:`window_splits` windows a dataset of
:data:`ceemx.datasets.REGISTRY` into train, validation and test :class:`~ceemx.Trajectories`,
normalised with statistics of the training part only.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.datasets.records import RawRecords, Record, load_records
from ceemx.datasets.registry import DatasetEntry, entry

__all__ = ["WindowSplits", "window_splits", "windows"]

_SMOKE_LENGTH = 32
_SMOKE_LIMITS = (4, 2, 2)  # train, valid, test windows of a smoke run


@dataclass(frozen=True)
class WindowSplits:
    """Windows of a dataset as normalised train/valid/test trajectories.

    Attributes:
        train: windows of the first part of the estimation record(s), y (B, T, 1), u (B, T, 1).
        valid: windows of the last part of the estimation record(s).
        test: windows of the official test record(s).
        y_mean: (1,) mean of y over the training part only; physical y = y_mean + y_std * y.
        y_std: (1,) standard deviation of y over the training part.
        u_mean: (1,) mean of u over the training part.
        u_std: (1,) standard deviation of u over the training part.
        dt: sample period [s].
        source: the data and the windowing, in words.
        output_names: one name per output.
    """

    train: Trajectories
    valid: Trajectories
    test: Trajectories
    y_mean: np.ndarray
    y_std: np.ndarray
    u_mean: np.ndarray
    u_std: np.ndarray
    dt: float
    source: str
    output_names: tuple[str, ...]


def windows(
    u: np.ndarray, y: np.ndarray, length: int, *, stride: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Cut one record into windows of ``length`` samples, starting every ``stride`` samples.

    Args:
        u: (N,) or (N, p) inputs.
        y: (N,) or (N, m) outputs.
        length: samples per window (>= 2).
        stride: step between window starts; ``None`` gives non-overlapping windows (``length``).

    Returns:
        ``(u_w, y_w)`` of shapes (W, length, p) and (W, length, m) with
        ``W = (N - length) // stride + 1``; window i is samples ``[i*stride, i*stride + length)``.
        The tail that does not fill a window is dropped.

    Raises:
        ValueError: for mismatched lengths, ``length < 2``, ``stride < 1`` or ``N < length``.
    """
    u = np.asarray(u, np.float64)
    y = np.asarray(y, np.float64)
    u = u[:, None] if u.ndim == 1 else u
    y = y[:, None] if y.ndim == 1 else y
    if u.ndim != 2 or y.ndim != 2 or u.shape[0] != y.shape[0]:
        raise ValueError(f"`u` and `y` must be (N, p) and (N, m); got {u.shape} and {y.shape}.")
    stride = length if stride is None else stride
    if length < 2 or stride < 1:
        raise ValueError(f"need `length` >= 2 and `stride` >= 1; got {length} and {stride}.")
    N = u.shape[0]
    if N < length:
        raise ValueError(f"a record of {N} samples holds no window of {length}.")
    starts = np.arange(0, N - length + 1, stride)
    idx = starts[:, None] + np.arange(length)
    return u[idx], y[idx]


def _cut(records: Sequence[Record], length: int, stride: int, limit: int | None):
    us, ys = zip(*(windows(u, y, length, stride=stride) for u, y in records), strict=True)
    u, y = np.concatenate(us), np.concatenate(ys)
    return (u[:limit], y[:limit]) if limit is not None else (u, y)


def _checked_tests(rec: RawRecords, spec: DatasetEntry, tests: Sequence[str] | None):
    """The test records to window: ``tests``, or the entry's default ones (checked)."""
    tests = spec.default_tests if tests is None else tuple(tests)
    unknown = [t for t in tests if t not in rec.tests]
    if unknown or not tests:
        raise ValueError(f"unknown test record(s) {unknown}; choose from {', '.join(rec.tests)}.")
    return tests


def _split_in_time(rec: RawRecords, fraction: float, length: int):
    """(fit part, validation part) of every estimation record: the last ``fraction`` validates."""
    fit_part, valid_part = [], []
    for u, y in rec.train.values():
        n_valid = max(int(round(fraction * u.shape[0])), length)
        fit_part.append((u[:-n_valid], y[:-n_valid]))
        valid_part.append((u[-n_valid:], y[-n_valid:]))
    return fit_part, valid_part


def _statistics(fit_part: Sequence[Record]):
    """(u mean, u std, y mean, y std) over the fit part; a zero std is replaced by 1."""
    u_fit = np.concatenate([u for u, _ in fit_part])
    y_fit = np.concatenate([y for _, y in fit_part])
    u_mean, u_std = u_fit.mean(0), u_fit.std(0)
    y_mean, y_std = y_fit.mean(0), y_fit.std(0)
    return u_mean, np.where(u_std > 0, u_std, 1.0), y_mean, np.where(y_std > 0, y_std, 1.0)


def window_splits(
    name: str,
    *,
    length: int | None = None,
    smoke: bool = False,
    root: str | os.PathLike | None = None,
    tests: Sequence[str] | None = None,
    verify: bool = True,
) -> WindowSplits:
    """Windows of a dataset as normalised train/valid/test :class:`~ceemx.Trajectories`.

    Each estimation record is split in time: its last part (a quarter for the tanks and drives, a
    fifth for Silverbox) gives the validation windows (non-overlapping), the rest the training
    windows (overlapping for the short records: stride 32 for the tanks, 20 for the drives). The
    test windows are non-overlapping windows of the official test record(s). Means and standard
    deviations come from the training part only, never from validation or test samples.

    Default window lengths: 128 (tanks, 512 s), 256 (Silverbox), 100 (drives).

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        length: window length (>= 26); ``None`` for the default.
        smoke: few short windows (length 32; at most 4 train, 2 valid and 2 test windows).
        root: the data folder (see :func:`ceemx.datasets.data_root`).
        tests: names of the official test records to window; ``None`` gives ``validation`` for
            the tanks, ``multisine`` for Silverbox and both sets for the drives.
        verify: check the file's sha256 (see :func:`ceemx.datasets.load_records`).

    Returns:
        A :class:`WindowSplits` with float64 data (when JAX runs in float64).

    Raises:
        ValueError: for an unknown name or test, ``length < 26``, or a length too long for the
            records.
        FileNotFoundError: when the data are missing.
    """
    spec = entry(name)
    rec = load_records(name, root, verify)
    if length is None:
        length = _SMOKE_LENGTH if smoke else spec.window_length
    if length < 26:
        raise ValueError(f"`length` must be >= 26; got {length}.")
    tests = _checked_tests(rec, spec, tests)
    fit_part, valid_part = _split_in_time(rec, spec.valid_fraction, length)
    limits = _SMOKE_LIMITS if smoke else (None, None, None)
    stride = max(1, min(spec.window_stride, length))
    try:
        splits = [
            _cut(fit_part, length, stride, limits[0]),
            _cut(valid_part, length, length, limits[1]),
            _cut([rec.tests[t] for t in tests], length, length, limits[2]),
        ]
    except ValueError as e:
        raise ValueError(f"{name}: window length {length} is too long for its records ({e})") from e
    u_mean, u_std, y_mean, y_std = _statistics(fit_part)
    sizes = "/".join(str(u.shape[0]) for u, _ in splits)
    source = (
        f"{name} ({rec.path.name}{', sha256 verified' if verify else ''}): {sizes} "
        f"train/valid/test windows of {length} samples; test = {', '.join(tests)}"
        + (" (smoke)" if smoke else "")
    )
    return WindowSplits(
        *[Trajectories((y - y_mean) / y_std, (u - u_mean) / u_std) for u, y in splits],
        y_mean=y_mean,
        y_std=y_std,
        u_mean=u_mean,
        u_std=u_std,
        dt=rec.dt,
        source=source,
        output_names=spec.output_names,
    )
