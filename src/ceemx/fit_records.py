"""The records of ``ceemx fit``: CSV and NPZ files read into NumPy arrays (no JAX imported).

CSV files have a header row of column names; an empty cell, ``nan``, ``NA``, ``n/a`` or
``null`` is a missing sample; any other text is refused with its line and column. NPZ files
hold one 1-D array per name. :func:`read_records` takes the output and input columns of every
file and the sample time from ``--dt`` or a time column (uniform sampling checked, the same in
every file). Every refusal is a :class:`Refused` with a one-line message.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Records", "Refused", "read_records"]

_MISSING = {"", "nan", "na", "n/a", "null"}


class Refused(ValueError):
    """A value the command refuses: one line on stderr, exit status 2."""


@dataclass(frozen=True)
class Records:
    """The records of the command, as NumPy arrays, and their metadata."""

    files: tuple[str, ...]
    ys: tuple[np.ndarray, ...]  # (T_b, m) each
    us: tuple[np.ndarray, ...] | None  # (T_b, p) each, None without inputs
    dt: float | None

    @property
    def shortest(self) -> int:
        """The number of samples of the shortest record."""
        return min(y.shape[0] for y in self.ys)


def _number(text: str, where: str) -> float:
    cell = text.strip()
    if cell.lower() in _MISSING:
        return math.nan
    try:
        return float(cell)
    except ValueError:
        raise Refused(f"{where}: {cell!r} is not a number") from None


def _read_csv(path: Path, wanted: Sequence[str]) -> dict[str, np.ndarray]:
    with path.open(newline="") as f:
        rows = csv.reader(f)
        try:
            header = [h.strip() for h in next(rows)]
        except StopIteration:
            raise Refused(f"{path}: the file is empty (expected a header row of names)") from None
        _check_columns(path, header, wanted)
        index = {name: header.index(name) for name in wanted}
        columns: dict[str, list[float]] = {name: [] for name in wanted}
        for line, row in enumerate(rows, start=2):
            if not any(cell.strip() for cell in row):
                continue  # a blank line
            for name, i in index.items():
                cell = row[i] if i < len(row) else ""
                columns[name].append(_number(cell, f"{path} line {line}, column {name!r}"))
    return {name: np.asarray(values, np.float64) for name, values in columns.items()}


def _read_npz(path: Path, wanted: Sequence[str]) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as archive:
            _check_columns(path, list(archive.files), wanted)
            arrays = {name: np.asarray(archive[name]) for name in wanted}
    except Refused:
        raise
    except (OSError, ValueError) as e:  # not a ZIP of .npy files, or an object array
        raise Refused(f"{path}: cannot read it as NPZ ({e})") from None
    for name, a in arrays.items():
        a = a[:, 0] if a.ndim == 2 and a.shape[1] == 1 else a
        if a.ndim != 1 or not np.issubdtype(a.dtype, np.number):
            raise Refused(f"{path}: {name!r} must be a 1-D numeric array; got {a.dtype}{a.shape}")
        arrays[name] = a.astype(np.float64)
    return arrays


def _check_columns(path: Path, have: Sequence[str], wanted: Sequence[str]) -> None:
    missing = [w for w in wanted if w not in have]
    if missing:
        names = ", ".join(repr(m) for m in missing)
        raise Refused(f"{path}: no column {names} (it has: {', '.join(have) or 'none'})")


def _sample_time(path: Path, t: np.ndarray) -> float:
    steps = np.diff(t)
    if steps.size == 0 or not np.all(np.isfinite(steps)):
        raise Refused(f"{path}: the time column must hold two or more finite times")
    dt = float(np.median(steps))
    if dt <= 0 or np.max(np.abs(steps - dt)) > 1e-6 * max(abs(dt), 1e-300) + 1e-12 * np.max(
        np.abs(t)
    ):
        raise Refused(
            f"{path}: the time column is not uniformly sampled (steps from {steps.min():.6g} to "
            f"{steps.max():.6g}); resample the record or give --dt"
        )
    return dt


def read_records(
    files: Sequence[str],
    outputs: Sequence[str],
    inputs: Sequence[str],
    *,
    dt: float | None = None,
    time: str | None = None,
) -> Records:
    """The records of ``files`` (CSV or NPZ): their output and input columns and sample time.

    Raises:
        Refused: a file that is not there or not readable, a missing column, a cell that is not
            a number, a non-uniform or disagreeing time column.
    """
    wanted = [*outputs, *inputs, *([time] if time else [])]
    ys, us, dts = [], [], []
    for name in files:
        path = Path(name)
        if not path.is_file():
            raise Refused(f"{name}: no such file")
        suffix = path.suffix.lower()
        if suffix == ".npz":
            cols = _read_npz(path, wanted)
        elif suffix in (".csv", ".txt"):
            cols = _read_csv(path, wanted)
        else:
            raise Refused(f"{name}: expected a .csv or .npz file")
        if len(cols[outputs[0]]) < 2:
            raise Refused(f"{name}: a record needs two or more samples")
        ys.append(np.stack([cols[c] for c in outputs], axis=-1))
        if inputs:
            us.append(np.stack([cols[c] for c in inputs], axis=-1))
        if time:
            dts.append(_sample_time(path, cols[time]))
    if dts and dt is None:
        first = dt = dts[0]
        for name, other in zip(files, dts, strict=True):
            if abs(other - first) > 1e-6 * first:
                raise Refused(
                    f"{name}: sample time {other:.6g}, {files[0]}: {first:.6g}; give --dt"
                )
    return Records(tuple(files), tuple(ys), tuple(us) if inputs else None, dt)
