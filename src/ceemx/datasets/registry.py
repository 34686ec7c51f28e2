"""The registry of the three real datasets: one entry per dataset holds everything about it.

An entry (:class:`DatasetEntry`) holds

- the official protocol (``nonlinear-benchmarks`` v1.0.1): the file and its published sha256,
  which samples of which columns form the estimation and test records, ``n_init``, the sample
  period, units, the unit published scores use, the published results, the citation;
- the default windows of :func:`ceemx.datasets.window_splits`;
- the dataset's gray-box model (:class:`GrayBox`: the :mod:`ceemx.systems.gray_box` model at
  its default guess, the hidden state the figures show, physical bounds, where a learned term
  enters) — the physics a user would write, not settings of a fit.

An entry holds no fitting settings (noise weighting, epochs, network size, windows, scoring
start): ``ceemx experiment real_data`` selects them on the training record by
:func:`ceemx.fit_hybrid`, the same way on every dataset.

Adding a dataset is adding an entry here (and its file's source in
:data:`ceemx.datasets.download.SOURCES`): the loaders, :func:`~ceemx.datasets.window_splits`
and ``ceemx experiment real_data`` read everything else from the entry.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ceemx.data.info import DataInfo
from ceemx.datasets.download import SOURCES, Source
from ceemx.models.system import AbstractSystem
from ceemx.systems.gray_box import CascadedTanks, CoupledDrives, Silverbox

__all__ = [
    "REGISTRY",
    "DatasetEntry",
    "GrayBox",
    "PublishedResult",
    "Segment",
    "entry",
]


@dataclass(frozen=True)
class Segment:
    """One record of a data file: samples ``[start, stop)`` of an input and an output column.

    Attributes:
        u: the input's column (0-based, in the file's order).
        y: the output's column.
        start: first sample.
        stop: one past the last sample (``None``: to the end of the file).
    """

    u: int
    y: int
    start: int = 0
    stop: int | None = None


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
class GrayBox:
    """A dataset's gray-box model and what fitting and plotting it needs to know.

    Attributes:
        factory: the physical initial guess, ``factory(*, dtype, **fields)`` (a model's
            ``default`` classmethod; ``fields`` override any field, e.g. ``process_noise``).
        hidden: the hidden state the figures show: its label and its index in x.
        options: structural options passed to ``factory`` (Silverbox: a first-order hold).
        bounds: physical bounds of the states, the ``lower=`` / ``upper=`` of
            :func:`ceemx.hybrid` (a learned term must respect them).
        targets: the equations a learned term enters (``True``: all of them), the ``dynamics=``
            of :func:`ceemx.hybrid`.
    """

    factory: Callable[..., AbstractSystem]
    hidden: tuple[str, int]
    options: Mapping[str, Any] = field(default_factory=dict)
    bounds: Mapping[str, Any] = field(default_factory=dict)
    targets: bool | tuple[int, ...] = True


@dataclass(frozen=True)
class DatasetEntry:
    """One real dataset: its official protocol and its gray-box model.

    Attributes:
        name: the dataset's name (its key in :data:`REGISTRY`).
        source: where the official file comes from, its path under a data folder and sha256.
        columns: the file's header (checked when read).
        train: the official estimation records by name.
        tests: the official test records by name.
        dt: sample period [s].
        n_init: test outputs a model may use to set its initial state (not scored).
        units: the signals' units, in words.
        output_names: one name per output.
        citation: the reference to cite for the data.
        score_unit: the unit published RMSEs use.
        score_scale: factor from the data's units to ``score_unit``.
        published: published results on the test records.
        test_names: test records renamed in a :class:`~ceemx.datasets.RealDataset`.
        window_length: default window length of :func:`~ceemx.datasets.window_splits`.
        window_stride: default stride of its training windows.
        valid_fraction: last part of each estimation record it keeps for validation.
        default_tests: the test records it windows by default.
        model: the gray-box model (:class:`GrayBox`).
        output_units, input_names, input_units: the channels' units and the inputs' names
            (with ``dt`` and ``output_names``: :attr:`info`, the records' metadata).
    """

    name: str
    source: Source
    columns: tuple[str, ...]
    train: Mapping[str, Segment]
    tests: Mapping[str, Segment]
    dt: float
    n_init: int
    units: str
    output_names: tuple[str, ...]
    citation: str
    score_unit: str
    score_scale: float
    published: tuple[PublishedResult, ...]
    window_length: int
    window_stride: int
    valid_fraction: float
    default_tests: tuple[str, ...]
    model: GrayBox
    test_names: Mapping[str, str] = field(default_factory=dict)
    output_units: tuple[str, ...] | None = None
    input_names: tuple[str, ...] | None = None
    input_units: tuple[str, ...] | None = None

    @property
    def info(self) -> DataInfo:
        """The records' metadata: sample time, channel names and units (``Trajectories.info``)."""
        return DataInfo(
            self.dt, "s", self.output_names, self.output_units, self.input_names, self.input_units
        )

    @property
    def file(self) -> str:
        """The data file's path under a data folder (``name/file.csv``)."""
        return self.source.file

    @property
    def sha256(self) -> str:
        """The published sha256 of the data file."""
        return self.source.sha256


_TANKS_NOTE = "most papers score all 1024 samples rather than dropping the first 50"

CASCADED_TANKS = DatasetEntry(
    name="cascaded_tanks",
    source=SOURCES["cascaded_tanks"],
    columns=("uEst", "uVal", "yEst", "yVal"),
    train={"estimation": Segment(u=0, y=2)},
    tests={"validation": Segment(u=1, y=3)},
    test_names={"validation": "test"},
    dt=4.0,
    n_init=50,
    units="u: pump voltage [V]; y: lower-tank level [V]",
    output_names=("lower tank level",),
    output_units=("V",),
    input_names=("pump voltage",),
    input_units=("V",),
    citation=(
        "M. Schoukens, P. Mattsson, T. Wigren, J.-P. Noël, 'Cascaded tanks benchmark combining "
        "soft and hard nonlinearities', Workshop on Nonlinear System Identification Benchmarks, "
        "2016."
    ),
    score_unit="V",
    score_scale=1.0,
    published=tuple(
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
    window_length=128,
    window_stride=32,
    valid_fraction=0.25,
    default_tests=("validation",),
    model=GrayBox(
        CascadedTanks.default,
        hidden=("upper-tank level x₁ [V]", 0),
        bounds={"lower": 0.0},  # tank levels are never negative
    ),
)

SILVERBOX = DatasetEntry(
    name="silverbox",
    source=SOURCES["silverbox"],
    columns=("V1", "V2"),
    train={"estimation": Segment(u=0, y=1, start=40650, stop=105712)},
    tests={
        "multisine": Segment(u=0, y=1, start=105712, stop=127400),
        "arrow_full": Segment(u=0, y=1, start=100, stop=40575),
        "arrow_no_extrapolation": Segment(u=0, y=1, start=100, stop=32100),
    },
    dt=1.0 / 610.35,
    n_init=50,
    units="u: V1 [V]; y: V2 [V] (scores are usually reported in mV)",
    output_names=("V2",),
    output_units=("V",),
    input_names=("V1",),
    input_units=("V",),
    citation=(
        "T. Wigren, J. Schoukens, 'Three free data sets for development and benchmarking in "
        "nonlinear system identification', European Control Conference (ECC), 2013."
    ),
    score_unit="mV",
    score_scale=1000.0,
    published=(
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
    window_length=256,
    window_stride=256,
    valid_fraction=0.2,
    default_tests=("multisine",),
    model=GrayBox(
        Silverbox.default,
        hidden=("scaled velocity ẏ/ω [V]", 1),
        # a first-order hold: the input is band-limited and sampled at ≈ 9 samples per period
        options={"hold": "foh"},
        targets=(1,),  # the missing physics is a force: the velocity equation of (y, ẏ/ω)
    ),
)

COUPLED_ELECTRIC_DRIVES = DatasetEntry(
    name="coupled_electric_drives",
    source=SOURCES["coupled_electric_drives"],
    columns=("u11", "u12", "z11", "z12"),
    train={
        "set1_low": Segment(u=0, y=2, stop=400),
        "set2_high": Segment(u=1, y=3, stop=400),
    },
    tests={
        "set1_low": Segment(u=0, y=2, start=400),
        "set2_high": Segment(u=1, y=3, start=400),
    },
    dt=0.02,
    n_init=10,
    units="u: motor input [V]; y: pulley speed from a sign-insensitive counter",
    output_names=("pulley speed",),
    output_units=("counter units",),
    input_names=("motor input",),
    input_units=("V",),
    citation=(
        "T. Wigren, M. Schoukens, 'Coupled electric drives data set and reference models', "
        "Technical report 2017-024, Department of Information Technology, Uppsala University, "
        "2017."
    ),
    score_unit="counter units",
    score_scale=1.0,
    published=(
        PublishedResult(
            "continuous-time subspace encoder (Beintema et al. 2023)",
            {"set1_low": 0.14, "set2_high": 0.10},
            "counter units",
            "median over runs, on a different split",
        ),
    ),
    window_length=100,
    window_stride=20,
    valid_fraction=0.25,
    default_tests=("set1_low", "set2_high"),
    model=GrayBox(CoupledDrives.default, hidden=("belt state x₂", 1)),
)

#: The real datasets by name.
REGISTRY: dict[str, DatasetEntry] = {
    e.name: e for e in (CASCADED_TANKS, SILVERBOX, COUPLED_ELECTRIC_DRIVES)
}


def entry(name: str) -> DatasetEntry:
    """The registry entry of dataset ``name``.

    Raises:
        ValueError: for an unknown name, naming the known ones.
    """
    if name not in REGISTRY:
        raise ValueError(f"unknown dataset {name!r}; choose from {', '.join(REGISTRY)}.")
    return REGISTRY[name]
