"""Three real measured nonlinear system-identification datasets, from the official CSV files.

The files are not part of the package. They are looked for in ``root`` (an argument), else in the
folder named by the ``CEEMX_DATA`` environment variable, else in the download cache, else in
``../shared/data`` relative to the working directory or to the repository (a development
checkout); else the official archive is downloaded into the cache on first use
(:mod:`ceemx.datasets.download`: `pooch`, the platform's cache folder or ``CEEMX_DATA_CACHE``;
offline, one sentence says where to put the file). Their sha256 is checked against the published
files.

=========================  =====================================  ==========================
name                       file                                   official test records
=========================  =====================================  ==========================
``cascaded_tanks``         ``cascaded_tanks/dataBenchmark.csv``   ``validation`` (``test`` in a
                                                                  :class:`RealDataset`)
``silverbox``              ``silverbox/SNLS80mV.csv``             ``multisine``, ``arrow_full``,
                                                                  ``arrow_no_extrapolation``
``coupled_electric_drives`` ``coupled_electric_drives/DATAUNIF.csv`` ``set1_low``, ``set2_high``
=========================  =====================================  ==========================

The official protocol (``nonlinear-benchmarks`` v1.0.1) lets a model use the whole test input and
the first ``n_init`` test outputs to set its initial state, and scores the free-run simulation RMSE
on ``y_test[n_init:]`` (:func:`ceemx.evaluation.metrics.benchmark_score`). Each dataset's protocol
is its entry in :data:`ceemx.datasets.REGISTRY`.

:func:`cascaded_tanks`, :func:`silverbox` and :func:`coupled_electric_drives` return a
:class:`RealDataset`: the official records as :class:`~ceemx.Trajectories` in physical units,
with ``n_init``, the sample period, units, citation and published results. :func:`load_records`
gives the raw (u, y) arrays, :func:`ceemx.datasets.window_splits` normalised windows for training.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ceemx.data.info import DataInfo
from ceemx.data.trajectories import Trajectories
from ceemx.datasets.download import data_file, sha256
from ceemx.datasets.registry import DatasetEntry, PublishedResult, Segment, entry

__all__ = [
    "RawRecords",
    "RealDataset",
    "cascaded_tanks",
    "coupled_electric_drives",
    "load_records",
    "real_dataset",
    "silverbox",
]

Record = tuple[np.ndarray, np.ndarray]
_verified: set[tuple[str, int, float]] = set()


@dataclass(frozen=True)
class RawRecords:
    """One dataset's official estimation and test records, as (u, y) pairs of (N, 1) arrays.

    Attributes:
        name: the dataset's name (a key of :data:`ceemx.datasets.REGISTRY`).
        train: the estimation record(s) by name: ``"estimation"``, or for the coupled drives
            ``"set1_low"`` (u11 → z11, first 400 samples) and ``"set2_high"`` (u12 → z12).
        tests: the official test records by name (see the module docstring).
        n_init: test outputs a model may use to set its initial state (not scored).
        dt: sample period [s].
        units: the signals' units, in words.
        citation: the reference to cite for the data.
        path: the file read.
    """

    name: str
    train: dict[str, Record]
    tests: dict[str, Record]
    n_init: int
    dt: float
    units: str
    citation: str
    path: Path = field(repr=False)


def _col(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float64).reshape(-1, 1)


def _verify(path: Path, spec: DatasetEntry) -> None:
    """Check the file's sha256 against the published one (once per file version per process)."""
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime)
    if key in _verified:
        return
    digest = sha256(path)
    if digest != spec.sha256:
        raise ValueError(
            f"sha256 of {path} is {digest}; expected {spec.sha256} (the published "
            f"{spec.name} file). Replace it with the official file or pass verify=False."
        )
    _verified.add(key)


def _read_columns(path: Path, spec: DatasetEntry) -> np.ndarray:
    """The file's data columns (N, len(columns)), its header checked."""
    with path.open() as f:
        header = [h.strip().strip('"') for h in f.readline().strip().rstrip(",").split(",")]
    if tuple(header[: len(spec.columns)]) != spec.columns:
        raise ValueError(f"{path}: expected columns {spec.columns}; got {tuple(header)}.")
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(len(spec.columns)), ndmin=2)


def _cut_records(d: np.ndarray, segments: Mapping[str, Segment]) -> dict[str, Record]:
    return {
        k: (_col(d[s.start : s.stop, s.u]), _col(d[s.start : s.stop, s.y]))
        for k, s in segments.items()
    }


def load_records(
    name: str,
    root: str | os.PathLike | None = None,
    verify: bool = True,
    *,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> RawRecords:
    """Read one dataset's official records.

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        root: the data folder (see :func:`ceemx.datasets.data_root`); ``None``: ``$CEEMX_DATA``,
            else the download cache (:func:`ceemx.datasets.data_file`).
        verify: check the file's sha256 against the published one (once per file per process).
        cache: the download cache (:func:`ceemx.datasets.download.cache_dir`).
        download: download the official file when it is not on disk (the first use).

    Returns:
        A :class:`RawRecords`; every signal is a float64 (N, 1) array.

    Raises:
        ValueError: for an unknown name, a sha256 mismatch or a file of the wrong shape.
        FileNotFoundError: when the file is missing under ``root`` / ``$CEEMX_DATA``, or is
            nowhere on disk and cannot be downloaded
            (:class:`~ceemx.datasets.download.DatasetUnavailable`).
    """
    spec = entry(name)
    path = data_file(name, root, cache=cache, download=download)
    if verify:
        _verify(path, spec)
    d = _read_columns(path, spec)
    return RawRecords(
        name,
        _cut_records(d, spec.train),
        _cut_records(d, spec.tests),
        spec.n_init,
        spec.dt,
        spec.units,
        spec.citation,
        path,
    )


@dataclass(frozen=True)
class RealDataset:
    """One dataset's official estimation and test records, unnormalised, in physical units.

    Attributes:
        name: the dataset's name (a key of :data:`ceemx.datasets.REGISTRY`).
        train: the full official estimation record(s), y and u of shape (B, T, 1) (B = 2 for the
            coupled drives, one record per set; 1 otherwise).
        train_names: one name per training record.
        tests: the official test records by name, each a (1, T, 1) :class:`~ceemx.Trajectories`.
        n_init: test outputs a model may use to set its initial state (not scored).
        dt: sample period [s].
        units: the signals' units, in words.
        score_unit: the unit published RMSEs use.
        score_scale: factor from the data's units to ``score_unit`` (``scale`` of
            :func:`ceemx.evaluation.metrics.benchmark_score`; 1000 for Silverbox, V → mV).
        citation: the reference to cite for the data.
        published: published results on the test records.
        output_names: one name per output.
        path: the file read.
        sha256: the published file's sha256; ``verified``: whether the file was checked.
    """

    name: str
    train: Trajectories
    train_names: tuple[str, ...]
    tests: dict[str, Trajectories]
    n_init: int
    dt: float
    units: str
    score_unit: str
    score_scale: float
    citation: str
    published: tuple[PublishedResult, ...]
    output_names: tuple[str, ...]
    path: Path = field(repr=False)
    sha256: str = field(repr=False)
    verified: bool = True


def _trajectories(records: Sequence[Record], info: DataInfo | None = None) -> Trajectories:
    y, u = np.stack([y for _, y in records]), np.stack([u for u, _ in records])
    return Trajectories(y, u, info=info)


def real_dataset(
    name: str,
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> RealDataset:
    """One dataset's official records as a :class:`RealDataset`.

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        root: the data folder (see :func:`ceemx.datasets.data_root`; else ``$CEEMX_DATA``,
            else the download cache: :func:`ceemx.datasets.data_file`).
        verify: check the file's sha256 against the published one (once per file per process).
        cache: the download cache (``None``: ``$CEEMX_DATA_CACHE`` or the platform's cache).
        download: download the official file on first use (``False``: only files on disk).

    Returns:
        A :class:`RealDataset` (float64 when JAX runs in float64).

    Raises:
        FileNotFoundError: naming the expected file and how to set the folder.
        ValueError: for an unknown name or a sha256 mismatch.
    """
    rec = load_records(name, root, verify, cache=cache, download=download)
    spec = entry(name)
    return RealDataset(
        name=name,
        train=_trajectories(list(rec.train.values()), spec.info),
        train_names=tuple(rec.train),
        tests={
            spec.test_names.get(k, k): _trajectories([r], spec.info) for k, r in rec.tests.items()
        },
        n_init=rec.n_init,
        dt=rec.dt,
        units=rec.units,
        score_unit=spec.score_unit,
        score_scale=spec.score_scale,
        citation=rec.citation,
        published=spec.published,
        output_names=spec.output_names,
        path=rec.path,
        sha256=spec.sha256,
        verified=verify,
    )


def cascaded_tanks(
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> RealDataset:
    """The cascaded-tanks dataset (Schoukens, Mattsson, Wigren, Noël 2016).

    A pump fills an upper tank that drains into a lower one; the upper level is hidden, the lower
    level saturates at 10 V (overflow). ``train``: (1, 1024, 1), (uEst, yEst); ``tests["test"]``:
    (1, 1024, 1), (uVal, yVal); ``n_init`` = 50; dt = 4 s; scores in V. See
    :func:`real_dataset` for the arguments (the file is downloaded into a user cache on first
    use) and errors.

    The level sensor has memory: each time the measured level falls through ≈ 5.5 V it drops by
    0.3–0.6 V in one sample (twice in ``train``, six times in the test record), which no model
    whose output is a function of its state can follow (docs/results.md, "The tanks' sensor").
    """
    return real_dataset("cascaded_tanks", root, verify=verify, cache=cache, download=download)


def silverbox(
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> RealDataset:
    """The Silverbox dataset (Wigren & Schoukens 2013), an electronic Duffing oscillator.

    u = V1, y = V2 [V], the velocity hidden; fs = 610.35 Hz. ``train``: samples [40650, 105712)
    (1, 65062, 1); ``tests``: ``"multisine"`` [105712, 127400), ``"arrow_full"`` [100, 40575),
    ``"arrow_no_extrapolation"`` [100, 32100); ``n_init`` = 50; scores in mV (``score_scale`` =
    1000). See :func:`real_dataset` for the arguments (the file is downloaded into a user cache
    on first use) and errors.
    """
    return real_dataset("silverbox", root, verify=verify, cache=cache, download=download)


def coupled_electric_drives(
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> RealDataset:
    """The coupled-electric-drives dataset (Wigren & Schoukens 2017), uniform-input sets.

    Two motors drive a pulley on a flexible belt; y is the pulley speed from a sign-insensitive
    counter, the belt states hidden. Per set (``"set1_low"``: u11 → z11, ``"set2_high"``:
    u12 → z12) samples [0, 400) train and [400, 500) test: ``train`` (2, 400, 1) (one record per
    set, ``train_names``), ``tests[set]`` (1, 100, 1); ``n_init`` = 10; dt = 20 ms. See
    :func:`real_dataset` for the arguments (the file is downloaded into a user cache on first
    use) and errors.
    """
    return real_dataset(
        "coupled_electric_drives", root, verify=verify, cache=cache, download=download
    )
