"""Three real measured nonlinear system-identification benchmarks, from the official CSV files.

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
                                                                  :class:`BenchmarkDataset`)
``silverbox``              ``silverbox/SNLS80mV.csv``             ``multisine``, ``arrow_full``,
                                                                  ``arrow_no_extrapolation``
``coupled_electric_drives`` ``coupled_electric_drives/DATAUNIF.csv`` ``set1_low``, ``set2_high``
=========================  =====================================  ==========================

The official protocol (``nonlinear-benchmarks`` v1.0.1) lets a model use the whole test input and
the first ``n_init`` test outputs to set its initial state, and scores the free-run simulation RMSE
on ``y_test[n_init:]`` (:func:`ceemx.evaluation.simulation.benchmark_score`).

:func:`cascaded_tanks`, :func:`silverbox` and :func:`coupled_electric_drives` return a
:class:`BenchmarkDataset`: the official records as :class:`~ceemx.Trajectories` in physical units,
with ``n_init``, the sample period, units, citation and published results. :func:`load_benchmark`
gives the raw (u, y) arrays, :func:`benchmark_splits` normalised windows for training.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.datasets.download import DatasetUnavailable, cache_dir, fetch

__all__ = [
    "BENCHMARKS",
    "BenchmarkDataset",
    "BenchmarkRecord",
    "PublishedResult",
    "WindowSplits",
    "benchmark_dataset",
    "benchmark_file",
    "benchmark_splits",
    "cascaded_tanks",
    "coupled_electric_drives",
    "data_root",
    "load_benchmark",
    "silverbox",
    "windows",
]

Record = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class _Spec:
    file: str
    sha256: str
    columns: tuple[str, ...]
    dt: float
    n_init: int
    units: str
    citation: str
    output_names: tuple[str, ...]
    length: int  # default window length
    stride: int  # default stride of training windows
    valid_fraction: float  # last part of each training record kept for validation
    default_tests: tuple[str, ...]


_TANKS_CITE = (
    "M. Schoukens, P. Mattsson, T. Wigren, J.-P. Noël, 'Cascaded tanks benchmark combining soft "
    "and hard nonlinearities', Workshop on Nonlinear System Identification Benchmarks, 2016."
)
_SILVER_CITE = (
    "T. Wigren, J. Schoukens, 'Three free data sets for development and benchmarking in nonlinear "
    "system identification', European Control Conference (ECC), 2013."
)
_DRIVES_CITE = (
    "T. Wigren, M. Schoukens, 'Coupled electric drives data set and reference models', Technical "
    "report 2017-024, Department of Information Technology, Uppsala University, 2017."
)

BENCHMARKS: dict[str, _Spec] = {
    "cascaded_tanks": _Spec(
        "cascaded_tanks/dataBenchmark.csv",
        "ef2388ed822f3aef4aa80d6b0f2b466dd80b361786b3eafc7a2957c31ea323a7",
        ("uEst", "uVal", "yEst", "yVal"),
        4.0,
        50,
        "u: pump voltage [V]; y: lower-tank level [V]",
        _TANKS_CITE,
        ("lower tank level",),
        128,
        32,
        0.25,
        ("validation",),
    ),
    "silverbox": _Spec(
        "silverbox/SNLS80mV.csv",
        "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1",
        ("V1", "V2"),
        1.0 / 610.35,
        50,
        "u: V1 [V]; y: V2 [V] (scores are usually reported in mV)",
        _SILVER_CITE,
        ("V2",),
        256,
        256,
        0.2,
        ("multisine",),
    ),
    "coupled_electric_drives": _Spec(
        "coupled_electric_drives/DATAUNIF.csv",
        "9114f637f22ca826f03f066270cf68bd8cad686739a7fa4b471c14ccdbf66889",
        ("u11", "u12", "z11", "z12"),
        0.02,
        10,
        "u: motor input [V]; y: pulley speed from a sign-insensitive counter",
        _DRIVES_CITE,
        ("pulley speed",),
        100,
        20,
        0.25,
        ("set1_low", "set2_high"),
    ),
}

_SILVER_TRAIN = (40650, 105712)
_SILVER_TESTS = {
    "multisine": (105712, 127400),
    "arrow_full": (100, 40575),
    "arrow_no_extrapolation": (100, 32100),
}
_SMOKE_LENGTH = 32
_verified: set[tuple[str, int, float]] = set()


@dataclass(frozen=True)
class BenchmarkRecord:
    """One benchmark's official estimation and test records, as (u, y) pairs of (N, 1) arrays.

    Attributes:
        name: the benchmark's name (a key of :data:`BENCHMARKS`).
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


@dataclass(frozen=True)
class WindowSplits:
    """Windows of a benchmark as normalised train/valid/test trajectories.

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


def _candidates(root: str | os.PathLike | None) -> list[Path]:
    if root is not None:
        return [Path(root)]
    env = os.environ.get("CEEMX_DATA")
    if env:
        return [Path(env)]
    return _checkout_folders()


def _checkout_folders() -> list[Path]:
    """``../shared/data`` of a development checkout: from the working directory and the repo."""
    repo = Path(__file__).resolve().parents[3]
    return [Path.cwd() / ".." / "shared" / "data", repo / ".." / "shared" / "data"]


def data_root(root: str | os.PathLike | None = None) -> Path:
    """The folder holding the benchmark files.

    Args:
        root: a folder to use; ``None`` tries ``$CEEMX_DATA``, then ``../shared/data`` relative to
            the working directory and to the repository.

    Returns:
        The first candidate folder that exists, resolved.

    Raises:
        FileNotFoundError: naming every folder tried.
    """
    tried = _candidates(root)
    for p in tried:
        if p.is_dir():
            return p.resolve()
    raise FileNotFoundError(
        "benchmark data folder not found; tried "
        + ", ".join(str(p) for p in tried)
        + ". Pass `root=` or set CEEMX_DATA to a folder holding cascaded_tanks/, silverbox/ and "
        "coupled_electric_drives/ with the official files."
    )


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _spec(name: str) -> _Spec:
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; choose from {', '.join(BENCHMARKS)}.")
    return BENCHMARKS[name]


def _col(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float64).reshape(-1, 1)


def benchmark_file(
    name: str,
    root: str | os.PathLike | None = None,
    *,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> Path:
    """Where a benchmark's official file is, downloading it into the cache on first use.

    Looked for in ``root``, else ``$CEEMX_DATA`` (either one given: the file must be there),
    else the cache (:func:`ceemx.datasets.download.cache_dir`), else ``../shared/data`` of a
    development checkout; else downloaded into the cache and checked
    (:func:`ceemx.datasets.download.fetch`).

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        root: the data folder (see :func:`data_root`).
        cache: the download cache (``None``: ``$CEEMX_DATA_CACHE`` or the platform's cache).
        download: allow the download (``False``: only files already on disk).

    Returns:
        The file's path (its sha256 is checked by the loaders, and after a download).

    Raises:
        FileNotFoundError: the file is not under ``root`` / ``$CEEMX_DATA``; or
            :class:`~ceemx.datasets.download.DatasetUnavailable` (a ``FileNotFoundError``) when
            it is nowhere on disk and cannot be downloaded — one sentence saying where to put it.
    """
    spec = _spec(name)
    if root is not None or os.environ.get("CEEMX_DATA"):
        try:
            path = data_root(root) / spec.file
        except FileNotFoundError as e:
            raise FileNotFoundError(f"{name}: cannot look for {spec.file}: {e}") from None
        if not path.is_file():
            raise FileNotFoundError(
                f"missing benchmark file {path}: the {name} benchmark needs the official "
                f"{spec.file} under the data folder. Pass `root=` (the folder holding "
                f"{spec.file.split('/')[0]}/) or set the CEEMX_DATA environment variable to it; "
                "with neither, the loaders download it into a user cache."
            )
        return path
    cached = cache_dir(cache) / spec.file
    if cached.is_file():
        return cached
    for folder in _checkout_folders():
        if (folder / spec.file).is_file():
            return (folder / spec.file).resolve()
    if not download:
        raise DatasetUnavailable(
            f"the {name} benchmark file is not on disk (looked for {cached}) and "
            "download=False: allow the download, or put the official file there or under a "
            f"folder named by CEEMX_DATA (as {spec.file})."
        )
    return fetch(name, cache=cache)


def load_benchmark(
    name: str,
    root: str | os.PathLike | None = None,
    verify: bool = True,
    *,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> BenchmarkRecord:
    """Read one benchmark's official records.

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        root: the data folder (see :func:`data_root`); ``None``: ``$CEEMX_DATA``, else the
            download cache (:func:`benchmark_file`).
        verify: check the file's sha256 against the published one (once per file per process).
        cache: the download cache (:func:`ceemx.datasets.download.cache_dir`).
        download: download the official file when it is not on disk (the first use).

    Returns:
        A :class:`BenchmarkRecord`; every signal is a float64 (N, 1) array.

    Raises:
        ValueError: for an unknown name, a sha256 mismatch or a file of the wrong shape.
        FileNotFoundError: when the file is missing under ``root`` / ``$CEEMX_DATA``, or is
            nowhere on disk and cannot be downloaded
            (:class:`~ceemx.datasets.download.DatasetUnavailable`).
    """
    path = benchmark_file(name, root, cache=cache, download=download)
    spec = _spec(name)
    if verify:
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime)
        if key not in _verified:
            digest = _sha256(path)
            if digest != spec.sha256:
                raise ValueError(
                    f"sha256 of {path} is {digest}; expected {spec.sha256} (the published "
                    f"{name} file). Replace it with the official file or pass verify=False."
                )
            _verified.add(key)
    with path.open() as f:
        header = [h.strip().strip('"') for h in f.readline().strip().rstrip(",").split(",")]
    if tuple(header[: len(spec.columns)]) != spec.columns:
        raise ValueError(f"{path}: expected columns {spec.columns}; got {tuple(header)}.")
    d = np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(len(spec.columns)), ndmin=2)
    if name == "cascaded_tanks":
        train = {"estimation": (_col(d[:, 0]), _col(d[:, 2]))}
        tests = {"validation": (_col(d[:, 1]), _col(d[:, 3]))}
    elif name == "silverbox":
        a, b = _SILVER_TRAIN
        train = {"estimation": (_col(d[a:b, 0]), _col(d[a:b, 1]))}
        tests = {k: (_col(d[a:b, 0]), _col(d[a:b, 1])) for k, (a, b) in _SILVER_TESTS.items()}
    else:
        train = {
            "set1_low": (_col(d[:400, 0]), _col(d[:400, 2])),
            "set2_high": (_col(d[:400, 1]), _col(d[:400, 3])),
        }
        tests = {
            "set1_low": (_col(d[400:, 0]), _col(d[400:, 2])),
            "set2_high": (_col(d[400:, 1]), _col(d[400:, 3])),
        }
    return BenchmarkRecord(
        name, train, tests, spec.n_init, spec.dt, spec.units, spec.citation, path
    )


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


def benchmark_splits(
    name: str,
    *,
    length: int | None = None,
    smoke: bool = False,
    root: str | os.PathLike | None = None,
    tests: Sequence[str] | None = None,
    verify: bool = True,
) -> WindowSplits:
    """Windows of a benchmark as normalised train/valid/test :class:`~ceemx.Trajectories`.

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
        root: the data folder (see :func:`data_root`).
        tests: names of the official test records to window; ``None`` gives ``validation`` for
            the tanks, ``multisine`` for Silverbox and both sets for the drives.
        verify: check the file's sha256 (see :func:`load_benchmark`).

    Returns:
        A :class:`WindowSplits` with float64 data (when JAX runs in float64).

    Raises:
        ValueError: for an unknown name or test, ``length < 26``, or a length too long for the
            records.
        FileNotFoundError: when the data are missing.
    """
    spec = _spec(name)
    rec = load_benchmark(name, root, verify)
    if length is None:
        length = _SMOKE_LENGTH if smoke else spec.length
    if length < 26:
        raise ValueError(f"`length` must be >= 26; got {length}.")
    stride = max(1, min(spec.stride, length))
    tests = spec.default_tests if tests is None else tuple(tests)
    unknown = [t for t in tests if t not in rec.tests]
    if unknown or not tests:
        raise ValueError(f"unknown test record(s) {unknown}; choose from {', '.join(rec.tests)}.")
    fit_part, valid_part = [], []
    for u, y in rec.train.values():
        n_valid = int(round(spec.valid_fraction * u.shape[0]))
        n_valid = max(n_valid, length)
        fit_part.append((u[:-n_valid], y[:-n_valid]))
        valid_part.append((u[-n_valid:], y[-n_valid:]))
    try:
        splits = [
            _cut(fit_part, length, stride, 4 if smoke else None),
            _cut(valid_part, length, length, 2 if smoke else None),
            _cut([rec.tests[t] for t in tests], length, length, 2 if smoke else None),
        ]
    except ValueError as e:
        raise ValueError(f"{name}: window length {length} is too long for its records ({e})") from e
    u_fit = np.concatenate([u for u, _ in fit_part])
    y_fit = np.concatenate([y for _, y in fit_part])
    u_mean, u_std = u_fit.mean(0), u_fit.std(0)
    y_mean, y_std = y_fit.mean(0), y_fit.std(0)
    u_std = np.where(u_std > 0, u_std, 1.0)
    y_std = np.where(y_std > 0, y_std, 1.0)
    trajs = [Trajectories((y - y_mean) / y_std, (u - u_mean) / u_std) for u, y in splits]
    sizes = "/".join(str(u.shape[0]) for u, _ in splits)
    source = (
        f"{name} ({rec.path.name}{', sha256 verified' if verify else ''}): {sizes} "
        f"train/valid/test windows of {length} samples; test = {', '.join(tests)}"
        + (" (smoke)" if smoke else "")
    )
    return WindowSplits(
        *trajs,
        y_mean=y_mean,
        y_std=y_std,
        u_mean=u_mean,
        u_std=u_std,
        dt=rec.dt,
        source=source,
        output_names=spec.output_names,
    )


# ---------------------------------------------------------------- the official records as datasets


@dataclass(frozen=True)
class PublishedResult:
    """A published free-run simulation RMSE to compare against (``shared/data/README.md``).

    Attributes:
        method: the method and its reference.
        rmse: RMSE by test name (empty where only a bound is reported; see ``note``).
        unit: the RMSE's unit (a dataset's ``score_unit``).
        note: where the number was scored differently from the official protocol.
    """

    method: str
    rmse: dict[str, float]
    unit: str
    note: str = ""


@dataclass(frozen=True)
class BenchmarkDataset:
    """One benchmark's official estimation and test records, unnormalised, in physical units.

    Attributes:
        name: the benchmark's name (a key of :data:`BENCHMARKS`).
        train: the full official estimation record(s), y and u of shape (B, T, 1) (B = 2 for the
            coupled drives, one record per set; 1 otherwise).
        train_names: one name per training record.
        tests: the official test records by name, each a (1, T, 1) :class:`~ceemx.Trajectories`.
        n_init: test outputs a model may use to set its initial state (not scored).
        dt: sample period [s].
        units: the signals' units, in words.
        score_unit: the unit published RMSEs use.
        score_scale: factor from the data's units to ``score_unit`` (``scale`` of
            :func:`ceemx.evaluation.simulation.benchmark_score`; 1000 for Silverbox, V → mV).
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


_TANKS_NOTE = "most papers score all 1024 samples rather than dropping the first 50"
_PUBLISHED = {
    "cascaded_tanks": (
        "V",
        1.0,
        tuple(
            PublishedResult(m, {"test": r}, "V", _TANKS_NOTE)
            for m, r in (
                ("gray-box model with a physical overflow term (Rogers et al. 2017)", 0.18),
                ("neural continuous-time state space (Forgione & Piga 2021)", 0.33),
                ("NLSS2, nonlinear state space, subspace initialisation (Relan et al. 2017)", 0.34),
                ("flexible state-space model, GP-inspired prior (Svensson & Schön 2017)", 0.45),
                ("Volterra, 3rd degree (Birpoutsoukis et al. 2018)", 0.54),
                ("best linear approximation (Relan et al. 2017)", 0.75),
            )
        ),
    ),
    "silverbox": (
        "mV",
        1000.0,
        (
            PublishedResult(
                "deep subspace encoder (Beintema, Tóth, Schoukens 2021), re-run",
                {"multisine": 2.0, "arrow_full": 5.8, "arrow_no_extrapolation": 2.0},
                "mV",
                "approximate (≈)",
            ),
            PublishedResult(
                "classic polynomial nonlinear state-space models",
                {},
                "mV",
                "reported well below 1 mV on arrow_no_extrapolation",
            ),
        ),
    ),
    "coupled_electric_drives": (
        "counter units",
        1.0,
        (
            PublishedResult(
                "continuous-time subspace encoder (Beintema et al. 2023)",
                {"set1_low": 0.14, "set2_high": 0.10},
                "counter units",
                "median over runs, on a different split",
            ),
        ),
    ),
}
_TEST_NAMES = {"cascaded_tanks": {"validation": "test"}}


def _trajectories(records: Sequence[Record]) -> Trajectories:
    return Trajectories(np.stack([y for _, y in records]), np.stack([u for u, _ in records]))


def benchmark_dataset(
    name: str,
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> BenchmarkDataset:
    """One benchmark's official records as a :class:`BenchmarkDataset`.

    Args:
        name: ``"cascaded_tanks"``, ``"silverbox"`` or ``"coupled_electric_drives"``.
        root: the data folder (see :func:`data_root`; else ``$CEEMX_DATA``, else the download
            cache: :func:`benchmark_file`).
        verify: check the file's sha256 against the published one (once per file per process).
        cache: the download cache (``None``: ``$CEEMX_DATA_CACHE`` or the platform's cache).
        download: download the official file on first use (``False``: only files on disk).

    Returns:
        A :class:`BenchmarkDataset` (float64 when JAX runs in float64).

    Raises:
        FileNotFoundError: naming the expected file and how to set the folder.
        ValueError: for an unknown name or a sha256 mismatch.
    """
    rec = load_benchmark(name, root, verify, cache=cache, download=download)
    spec = BENCHMARKS[name]
    unit, scale, published = _PUBLISHED[name]
    rename = _TEST_NAMES.get(name, {})
    return BenchmarkDataset(
        name=name,
        train=_trajectories(list(rec.train.values())),
        train_names=tuple(rec.train),
        tests={rename.get(k, k): _trajectories([r]) for k, r in rec.tests.items()},
        n_init=rec.n_init,
        dt=rec.dt,
        units=rec.units,
        score_unit=unit,
        score_scale=scale,
        citation=rec.citation,
        published=published,
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
) -> BenchmarkDataset:
    """The cascaded-tanks benchmark (Schoukens, Mattsson, Wigren, Noël 2016).

    A pump fills an upper tank that drains into a lower one; the upper level is hidden, the lower
    level saturates at 10 V (overflow). ``train``: (1, 1024, 1), (uEst, yEst); ``tests["test"]``:
    (1, 1024, 1), (uVal, yVal); ``n_init`` = 50; dt = 4 s; scores in V. See
    :func:`benchmark_dataset` for the arguments (the file is downloaded into a user cache on
    first use) and errors.

    The level sensor has memory: each time the measured level falls through ≈ 5.5 V it drops by
    0.3–0.6 V in one sample (twice in ``train``, six times in the test record), which no model
    whose output is a function of its state can follow (docs/results.md, "The tanks' sensor").
    """
    return benchmark_dataset("cascaded_tanks", root, verify=verify, cache=cache, download=download)


def silverbox(
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> BenchmarkDataset:
    """The Silverbox benchmark (Wigren & Schoukens 2013), an electronic Duffing oscillator.

    u = V1, y = V2 [V], the velocity hidden; fs = 610.35 Hz. ``train``: samples [40650, 105712)
    (1, 65062, 1); ``tests``: ``"multisine"`` [105712, 127400), ``"arrow_full"`` [100, 40575),
    ``"arrow_no_extrapolation"`` [100, 32100); ``n_init`` = 50; scores in mV (``score_scale`` =
    1000). See :func:`benchmark_dataset` for the arguments (the file is downloaded into a user
    cache on first use) and errors.
    """
    return benchmark_dataset("silverbox", root, verify=verify, cache=cache, download=download)


def coupled_electric_drives(
    root: str | os.PathLike | None = None,
    *,
    verify: bool = True,
    cache: str | os.PathLike | None = None,
    download: bool = True,
) -> BenchmarkDataset:
    """The coupled-electric-drives benchmark (Wigren & Schoukens 2017), uniform-input sets.

    Two motors drive a pulley on a flexible belt; y is the pulley speed from a sign-insensitive
    counter, the belt states hidden. Per set (``"set1_low"``: u11 → z11, ``"set2_high"``:
    u12 → z12) samples [0, 400) train and [400, 500) test: ``train`` (2, 400, 1) (one record per
    set, ``train_names``), ``tests[set]`` (1, 100, 1); ``n_init`` = 10; dt = 20 ms. See
    :func:`benchmark_dataset` for the arguments (the file is downloaded into a user cache on
    first use) and errors.
    """
    return benchmark_dataset(
        "coupled_electric_drives", root, verify=verify, cache=cache, download=download
    )
