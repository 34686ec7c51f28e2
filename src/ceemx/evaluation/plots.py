"""Figures a person can read: benchmark traces and residual correlations, from plain arrays.

- :func:`plot_benchmark` — measured and simulated outputs of one record (one or several models)
  over the whole record and, beside it, a zoomed window; the simulation error y − ŷ on its own
  axis below; optionally hidden states with their physical meaning and bounds (and a note when a
  state leaves them). The initial-state window (not scored) is shaded grey, the zoomed window
  marked yellow on the whole-record panels; axis limits follow the measured output, so a
  diverging model cannot squash the data (its legend entry still gives its RMSE). The panels:
  :mod:`ceemx.evaluation.trace_panels`.
- :func:`plot_resid` — the autocorrelation of residuals and their cross-correlation with each
  input, with the pointwise 99 % band ±2.58/√N, as MATLAB's ``resid`` draws them (the numbers:
  :func:`ceemx.identification.analysis.correlations.residual_correlations`).
- :func:`plot_residual_diagnostics` — the figure of :meth:`ceemx.FitResult.diagnostics`.
- :func:`plot_profile` — the figure of :meth:`ceemx.FitResult.profile`: the profile's drop
  2·(max − profile) against the parameter, the threshold, the profile and Wald intervals.

Each returns a Matplotlib ``Figure`` (Agg backend; :func:`ceemx.evaluation.report.save_figure`
writes it atomically) or draws into the ``fig`` given — a ``SubFigure`` too, so that several
records share one file::

    fig = report.plt().figure(figsize=(11, 9), layout="constrained")
    for sub, (name, rec) in zip(fig.subfigures(len(records), 1), records.items()):
        plot_benchmark(rec["y"], {"gray-box": rec["y_sim"]}, n_init=n_init, title=name, fig=sub)

Records of tens of thousands of samples are drawn, over the whole record, as the band between the
minimum and maximum of each of ``max_points / 2`` bins (display only: the envelope is exact, the
file small); the zoomed window shows every sample.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from jaxtyping import ArrayLike

from ceemx.data.info import DataInfo
from ceemx.evaluation.report import plt, save_figure
from ceemx.evaluation.trace_panels import (
    Bounds,
    TracePanels,
    axes_grid,
    draw_hidden,
    draw_outputs,
    label_time_axes,
    zoom_window,
)
from ceemx.identification.analysis.correlations import BAND_Z, residual_correlations

__all__ = ["FONTS", "plot_benchmark", "plot_profile", "plot_resid", "plot_residual_diagnostics"]

#: Matplotlib settings of every figure here: text readable at the saved size (≈ 11 in wide).
FONTS: dict[Any, Any] = {
    "font.size": 10,
    "axes.titlesize": 10,
    "axes.labelsize": 10,
    "legend.fontsize": 8.5,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "axes.spines.top": False,
    "axes.spines.right": False,
}

_BAND = "#c6dbef"
_OUT = "#d62728"


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _as_tm(values: ArrayLike, name: str) -> np.ndarray:
    """(T, m) float64 from (T,), (T, m) or one record (1, T, m)."""
    a = np.asarray(values, np.float64)
    if a.ndim == 3 and a.shape[0] == 1:
        a = a[0]
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise ValueError(
            f"`{name}` must be one record, (T,), (T, m) or (1, T, m); got shape {a.shape} "
            "(plot each record of a batch on its own: fig.subfigures)."
        )
    return a


def _names(given: str | Sequence[str] | None, k: int, default: str, what: str) -> list[str]:
    if given is None:
        return [default if k == 1 else f"{default} {i + 1}" for i in range(k)]
    names = [given] if isinstance(given, str) else list(given)
    if len(names) != k:
        raise ValueError(f"`{what}` needs {k} name{'s' if k != 1 else ''}; got {len(names)}.")
    return names


def _new_figure(fig, size: tuple[float, float]):
    if fig is not None:
        return fig
    return plt().figure(figsize=size, layout="constrained")


# --------------------------------------------------------------------------------------------
# Benchmark traces
# --------------------------------------------------------------------------------------------


def plot_benchmark(
    y: ArrayLike,
    y_sim: ArrayLike | Mapping[str, ArrayLike],
    *,
    n_init: int = 0,
    zoom: tuple[int, int] | str | bool | None = None,
    zoom_fraction: float | int = 0.05,
    zoom_samples: int = 600,
    hidden: ArrayLike | None = None,
    hidden_label: str | Sequence[str] | None = None,
    bounds: Sequence[Any] | None = None,
    label: str = "simulated",
    output_names: str | Sequence[str] | None = None,
    unit: str = "",
    score_scale: float | int = 1.0,
    score_unit: str | None = None,
    dt: float | int | None = None,
    title: str | None = None,
    max_points: int = 3000,
    fig: Any = None,
):
    """Measured vs simulated outputs of one record, the error, and hidden states, readable.

    Rows of two panels, the whole record and the zoomed window (module notes): per output, the
    measured output (black) and each model's free-run simulation (legend: its RMSE on samples
    ``n_init:``), then their errors y − ŷ; then one row per hidden state with its physical range
    (dashed, the region outside shaded; a note says how often and how far the state leaves it).

    Args:
        y: the measured output of one record: (T,), (T, m) or (1, T, m) (NaN: missing), or
            the record itself (a one-record :class:`~ceemx.Trajectories`, e.g. ``test[0:1]``):
            its :class:`~ceemx.DataInfo` then gives the default names, unit and ``dt``.
        y_sim: the simulated output, same shape, or several models' as ``{name: y_sim}`` (in
            legend order; the first one's largest error places the default zoom).
        n_init: samples used to estimate the initial state (not scored).
        zoom: the zoomed window: ``"error"`` (default, ``None``): ``zoom_fraction`` of the record
            centred on the first model's largest error after ``n_init``; ``"start"``: from just
            before ``n_init``; ``(start, stop)`` sample indices; ``False``: no zoomed panels.
        zoom_fraction: the default window's share of the record (at least 20 samples) …
        zoom_samples: … and at most this many samples (a few dozen periods of the dynamics: a
            wider window of a fast oscillation is a band again).
        hidden: hidden states of one model to show: (T,) or (T, k) (e.g. a column of
            :attr:`~ceemx.evaluation.metrics.BenchmarkScore.x_sim`).
        hidden_label: what each hidden state is, with its unit, e.g. ``"upper-tank level x₁ [V]"``.
        bounds: the physical range of each hidden state, ``(low, high)`` (``None`` for an open
            side), or one such pair per state.
        label: the legend name of ``y_sim`` when it is one array.
        output_names: a name per output (default ``y``, ``y 1``, …).
        unit: the outputs' unit (axis labels).
        score_scale: the RMSE in the legend is multiplied by it (e.g. 1000 for mV from V).
        score_unit: the RMSE's unit in the legend (default ``unit``).
        dt: the sampling interval in seconds: time on the x-axis instead of samples.
        title: a title over the figure.
        max_points: above this many samples, the min/max band of ``max_points / 2`` bins.
        fig: a ``Figure`` or ``SubFigure`` to draw into (default: a new one, 11 in wide).

    Returns:
        The figure (``report.save_figure(fig, path)`` writes and closes it).

    Raises:
        ValueError, TypeError: shapes that do not match, or a bad ``zoom``, name count or
            numeric option (``n_init``, ``max_points``, ``dt``, …: named).

    Example:
        >>> import numpy as np
        >>> from ceemx.evaluation.plots import plot_benchmark
        >>> t = np.arange(500)
        >>> y = np.sin(t / 10)
        >>> fig = plot_benchmark(y, {"model": 0.9 * y}, n_init=10, hidden=np.cos(t / 10),
        ...                      hidden_label="velocity", bounds=(-1, 1))
        >>> len(fig.axes)
        6
    """
    y, output_names, unit, dt = _from_record(y, output_names, unit, dt)
    _check_plot_options(zoom_fraction, zoom_samples, score_scale, dt, max_points)
    rec = _record(y, y_sim, label, n_init, output_names, hidden, hidden_label, bounds)
    panels = _panels(rec, zoom, zoom_fraction, int(zoom_samples), dt, max_points)
    legend_unit = unit if score_unit is None else score_unit
    with plt().rc_context(FONTS):
        fig = _draw_record(fig, panels, rec, unit, legend_unit, score_scale)
        if title:
            fig.suptitle(title, x=0.01, ha="left", fontweight="bold")
    return fig


def _from_record(y, output_names, unit: str, dt):
    """``y`` as arrays, with the defaults a record (one-record ``Trajectories``) carries.

    Its outputs (masked samples NaN), and its ``DataInfo``'s output names, unit and sample time
    where the call gives none. Arrays pass through.
    """
    if not (hasattr(y, "mask") and hasattr(y, "info")):
        return y, output_names, unit, dt
    info = y.info if y.info is not None else DataInfo()
    if y.batch_size != 1:
        raise ValueError(f"`y`: one record (e.g. data[i : i + 1]); got {y.batch_size} records.")
    values = np.where(np.asarray(y.mask), np.asarray(y.y, np.float64), np.nan)[0]
    units = set(info.output_units or ())
    if not unit and len(units) == 1:
        unit = units.pop()
    if dt is None and info.dt is not None and info.time_unit == "s":
        dt = info.dt
    return values, info.output_names if output_names is None else output_names, unit, dt


def _check_plot_options(zoom_fraction, zoom_samples, score_scale, dt, max_points) -> None:
    """:func:`plot_benchmark`'s numeric options, each named when it is not what it must be."""
    _positive("zoom_fraction", zoom_fraction, upper=1.0)
    _count("zoom_samples", zoom_samples, 1)
    _count("max_points", max_points, 2)
    _positive("score_scale", score_scale)
    if dt is not None:
        _positive("dt", dt)


def _count(name: str, value, low: int, high: int = 2**31 - 1) -> int:
    """``value`` as an int in [low, high] (a bool is not one), else an error naming it."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"`{name}` must be an integer; got {value!r}.")
    if not low <= value <= high:
        raise ValueError(f"`{name}` must be an integer in [{low}, {high}]; got {value!r}.")
    return int(value)


def _positive(name: str, value, upper: float = math.inf) -> None:
    """Raise unless ``value`` is a real number in (0, ``upper``] (finite)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"`{name}` must be a real number; got {value!r}.")
    if not (math.isfinite(value) and 0 < value <= upper):
        bound = "finite and > 0" if upper == math.inf else f"in (0, {upper:g}]"
        raise ValueError(f"`{name}` must be {bound}; got {value!r}.")


class _Record(NamedTuple):
    """One record's arrays for :func:`plot_benchmark`, checked."""

    y: np.ndarray  # (T, m)
    sims: dict[str, np.ndarray]  # {name: (T, m)}
    n_init: int
    names: list[str]  # per output
    hidden: np.ndarray | None  # (T, k)
    hidden_names: list[str]  # per hidden state
    bounds: list[Bounds]  # per hidden state


def _record(y, y_sim, label, n_init, output_names, hidden, hidden_label, bounds) -> _Record:
    """The arguments of :func:`plot_benchmark` checked, in the order of its signature."""
    yy = _as_tm(y, "y")
    T, m = yy.shape
    sims = _simulations(y_sim, label, yy.shape)
    n_init = _count("n_init", n_init, 0, T - 1)
    names = _names(output_names, m, "y", "output_names")
    return _Record(yy, sims, n_init, names, *_hidden_states(hidden, hidden_label, bounds, T))


def _panels(rec: _Record, zoom, fraction: float, max_samples: int, dt, max_points: int):
    """The x-axis of the figure: sample times, the initial-state window, the zoomed window."""
    T = rec.y.shape[0]
    first = next(iter(rec.sims.values()))  # its largest error places the default zoom
    window = zoom_window(zoom, rec.y - first, rec.n_init, T, fraction, max_samples)
    x = np.arange(T) * (1.0 if dt is None else float(dt))
    return TracePanels(x, rec.n_init, window, max_points, in_samples=dt is None)


def _draw_record(fig, panels: TracePanels, rec: _Record, unit: str, score_unit: str, scale):
    """The rows of a benchmark figure: per output (output, error), then per hidden state."""
    m = rec.y.shape[1]
    heights = [2.3, 1.3] * m + [1.5] * len(rec.hidden_names)
    fig = _new_figure(fig, (11.0, 0.9 + 1.25 * sum(heights)))
    rows = axes_grid(fig, heights, panels.window is not None)
    draw_outputs(panels, rows, rec.y, rec.sims, names=rec.names, unit=unit,
                 score_unit=score_unit, score_scale=scale)  # fmt: skip
    for i, name in enumerate(rec.hidden_names):
        assert rec.hidden is not None
        draw_hidden(panels, rows[2 * m + i], rec.hidden[:, i], name, rec.bounds[i])
    label_time_axes(rows, "sample" if panels.in_samples else "time [s]")
    return fig


def _simulations(
    y_sim: ArrayLike | Mapping[str, ArrayLike], label: str, shape: tuple[int, ...]
) -> dict[str, np.ndarray]:
    """``{name: (T, m) simulation}`` from one array or a mapping, each of the measured shape."""
    sims_in = dict(y_sim) if isinstance(y_sim, Mapping) else {label: y_sim}
    if not sims_in:
        raise ValueError("`y_sim` is empty: give at least one simulation.")
    sims = {}
    for name, s in sims_in.items():
        s = _as_tm(s, f"y_sim[{name!r}]")
        if s.shape != shape:
            raise ValueError(f"y_sim[{name!r}] has shape {s.shape}; y has {shape}.")
        sims[name] = s
    return sims


def _hidden_states(
    hidden: ArrayLike | None,
    hidden_label: str | Sequence[str] | None,
    bounds: Sequence[Any] | None,
    T: int,
) -> tuple[np.ndarray | None, list[str], list[Bounds]]:
    """(T, k) hidden states (``None``: none), a label and a physical range (or None) per state."""
    hid = None if hidden is None else _as_tm(hidden, "hidden")
    if hid is not None and hid.shape[0] != T:
        raise ValueError(f"`hidden` has {hid.shape[0]} samples; y has {T}.")
    k = 0 if hid is None else hid.shape[1]
    names = _names(hidden_label, k, "hidden state", "hidden_label") if k else []
    ranges: list[Bounds] = [None] * k
    if bounds is not None and k:
        pair = len(bounds) == 2 and all(b is None or np.isscalar(b) for b in bounds)
        given = [bounds] if pair else list(bounds)
        if len(given) != k:
            raise ValueError(f"`bounds` needs {k} (low, high) pairs; got {len(given)}.")
        ranges = [None if b is None else (b[0], b[1]) for b in given]  # type: ignore[index]
    return hid, names, ranges


# --------------------------------------------------------------------------------------------
# Residual correlations
# --------------------------------------------------------------------------------------------


def _correlation_axis(ax, ks, r, band, title: str, xlabel: str, *, legend: bool = False) -> None:
    """Stems of r at lags ks, those outside the band red, the band shaded and edged."""
    r = np.asarray(r, float)
    band = np.broadcast_to(np.asarray(band, float), r.shape)
    ax.fill_between(ks, -band, band, step="mid", color=_BAND, lw=0, zorder=0,
                    label=f"99 % band ±{BAND_Z:.2f}/√N")  # fmt: skip
    ax.step(ks, band, where="mid", color="C0", lw=0.7, ls="--", zorder=1)
    ax.step(ks, -band, where="mid", color="C0", lw=0.7, ls="--", zorder=1)
    ax.axhline(0.0, color="0.3", lw=0.6)
    out = np.abs(r) > band
    for mask, color, lab in ((~out, "0.25", "inside"), (out, _OUT, "outside the band")):
        if mask.any():
            ax.vlines(ks[mask], 0.0, r[mask], color=color, lw=1.2, zorder=2)
            ax.plot(ks[mask], r[mask], "o", color=color, ms=3.2, zorder=3, label=lab)
    finite = np.isfinite(r)
    lim = max(1.3 * float(np.max(band)), 1.15 * float(np.max(np.abs(r[finite]), initial=0.0)))
    ax.set_ylim(-lim, lim)
    ax.set_title(title, loc="left")
    ax.set_xlabel(xlabel)
    if legend:
        ax.legend(loc="upper right", frameon=True, framealpha=0.85)


def plot_resid(
    residuals: ArrayLike,
    inputs: ArrayLike | None = None,
    *,
    lags: int = 25,
    output_names: str | Sequence[str] | None = None,
    input_names: str | Sequence[str] | None = None,
    what: str = "residuals",
    title: str | None = None,
    fig: Any = None,
):
    """Residual autocorrelation and input cross-correlation with 99 % bands (MATLAB ``resid``).

    One row per output: the autocorrelation r(k) of the residuals at lags 1…M, then one panel per
    input with the cross-correlation of e_t and u_{t−k} at lags −M…M (k > 0: the input before
    the error — the model misses how the input acts; k < 0: feedback). The shaded band is the
    pointwise 99 % band ±2.58/√N_k of white residuals independent of the input; stems outside it
    are red. (A correct model still puts about 1 lag in 100 outside; the tests of
    :func:`ceemx.residual_diagnostics` take that into account.)

    Args:
        residuals: e, (T,), (T, m) or (B, T, m): one-step prediction errors (as ``resid``) or
            free-run simulation errors y − ŷ (these are correlated whenever the noise acts on the
            state; read them as a check of the input–output dynamics). NaN: missing.
        inputs: u, (T,), (T, p) or (B, T, p), or ``None`` (autocorrelation only).
        lags: M, the largest lag.
        output_names: a name per output (default ``y``, ``y 1``, …).
        input_names: a name per input (default ``u``, ``u 1``, …).
        what: what the residuals are, for the titles.
        title: a title over the figure.
        fig: a ``Figure`` or ``SubFigure`` to draw into (default: a new one).

    Returns:
        The figure.

    Example:
        >>> import numpy as np
        >>> from ceemx.evaluation.plots import plot_resid
        >>> rng = np.random.default_rng(0)
        >>> fig = plot_resid(rng.normal(size=400), rng.normal(size=400), lags=20)
        >>> len(fig.axes)
        2
    """
    c = residual_correlations(residuals, inputs, lags=lags)
    m, p = c.cross_correlation.shape[:2]
    M = c.lags
    out_names = _names(output_names, m, "y", "output_names")
    in_names = _names(input_names, p, "u", "input_names")
    band, xband = c.band(), c.cross_band()
    pyplot = plt()
    with pyplot.rc_context(FONTS):
        fig = _new_figure(fig, (4.2 * (1 + p), 0.6 + 2.6 * m))
        grid = fig.add_gridspec(m, 1 + p)
        for i in range(m):
            ax = fig.add_subplot(grid[i, 0])
            ks = np.arange(1, M + 1)
            _correlation_axis(ax, ks, c.autocorrelation[i, 1:], band[i, 1:],
                              f"autocorrelation of {what}: {out_names[i]}", "lag k",
                              legend=i == 0)  # fmt: skip
            for j in range(p):
                ax = fig.add_subplot(grid[i, 1 + j])
                ks = np.arange(-M, M + 1)
                _correlation_axis(ax, ks, c.cross_correlation[i, j], xband[i, j],
                                  f"{in_names[j]} and {what} ({out_names[i]})",
                                  f"lag k ({what} at t, {in_names[j]} at t − k)")  # fmt: skip
        if title:
            fig.suptitle(title, x=0.01, ha="left", fontweight="bold")
    return fig


def _verdict(value, passed: str, failed: str) -> str:
    """A test's verdict for a panel title: passed, failed, or not tested (``None``)."""
    if value is None:
        return "not tested"
    return passed if value else failed


def plot_residual_diagnostics(diag, path: str | os.PathLike | None = None):
    """The figure of a :class:`~ceemx.identification.analysis.diagnostics.ResidualDiagnostics`.

    One row per output: the autocorrelation of the standardised one-step prediction errors at
    lags 1…M and their cross-correlation with every input at lags −M…M, each with the pointwise
    99 % band ±2.58/√N_k (as MATLAB's ``resid`` draws them; stems outside in red); a last row:
    the noise ratios per component on a log axis — one E-step's realised / assumed variance and,
    when estimated, (estimated / assumed std)² — with the consistency band [1/F, F].

    Args:
        diag: the diagnostics (:meth:`ceemx.FitResult.diagnostics`).
        path: the figure file (its suffix picks the format), written atomically; ``None``: return
            the figure instead.

    Returns:
        The path written, or the figure when ``path`` is ``None``.
    """
    acf = np.asarray(diag.autocorrelation)
    xcf = np.asarray(diag.cross_correlation)
    m, p = xcf.shape[0], xcf.shape[1]
    M = int(diag.lags)
    pairs = np.asarray(diag.pair_counts)
    band = BAND_Z / np.sqrt(np.maximum(pairs, 1))
    pyplot = plt()
    with pyplot.rc_context(FONTS):
        fig = pyplot.figure(figsize=(4.2 * (1 + p), 2.7 * (m + 1)), layout="constrained")
        grid = fig.add_gridspec(m + 1, 1 + p)
        for i in range(m):
            ax = fig.add_subplot(grid[i, 0])
            verdict = _verdict(diag.white[i], "white", "NOT white")
            _correlation_axis(ax, np.arange(1, M + 1), acf[i, 1:], band[i, 1:],
                              f"output {i + 1}: autocorrelation ({verdict}; NIS {diag.nis[i]:.3g})",
                              "lag k", legend=i == 0)  # fmt: skip
            for j in range(p):
                ax = fig.add_subplot(grid[i, 1 + j])
                xb = BAND_Z / math.sqrt(max(float(diag.counts[i]), 1.0))
                ok = _verdict(diag.independent[i, j], "independent", "CORRELATED")
                _correlation_axis(ax, np.arange(-M, M + 1), xcf[i, j], xb,
                                  f"output {i + 1} and input {j + 1} ({ok})",
                                  "lag k (error at t, input at t − k)")  # fmt: skip
        ax = fig.add_subplot(grid[m, :])
        names, ratio, em = [], [], []
        for name, what in (("process_noise", "state"), ("obs_noise", "output")):
            r = np.asarray(diag.noise_ratios[name], float)
            for c in range(r.size):
                names.append(f"{name}\n{what} {c + 1}")
                ratio.append(r[c])
                if diag.estimated_std is not None:
                    em.append((diag.estimated_std[name][c] / diag.assumed_std[name][c]) ** 2)
        x = np.arange(len(names))
        width = 0.4 if em else 0.8
        ax.bar(x - (width / 2 if em else 0), ratio, width, label="one E-step: realised / assumed")
        if em:
            ax.bar(x + width / 2, em, width, label="(estimated / assumed std)²")
        F = float(diag.factor)
        ax.axhspan(1 / F, F, color="0.88", zorder=0, label=f"consistent [1/{F:g}, {F:g}]")
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_yscale("log")
        ax.set_xticks(x, names)
        ax.set_ylabel("variance ratio")
        ax.set_title("noise ratios", loc="left")
        ax.legend(loc="upper right")
    if path is None:
        return fig
    return save_figure(fig, Path(path))


def plot_profile(profile, path: str | os.PathLike | None = None, *, ax: Any = None) -> Any:
    """The figure of a :class:`~ceemx.identification.analysis.profile.Profile`.

    The drop 2·(max − profile) at every point computed (joined in order of the parameter: the
    search's few points, or a curve with ``FitResult.profile(name, grid=20)``), the threshold
    χ²₁(level) (dashed), the profile interval (shaded; an end at the bound or the search limit
    says so) and the Wald interval (a bar on the threshold line).

    Args:
        profile: the profile (:meth:`ceemx.FitResult.profile`).
        path: the figure file (its suffix picks the format), written atomically; ``None``: return
            the figure instead.
        ax: draw into these axes instead of a new figure (``path`` is then ignored).

    Returns:
        The path written, or the figure when ``path`` is ``None``.
    """
    pts = np.asarray(profile.points, np.float64).reshape(-1, 2)
    ok = np.isfinite(pts[:, 1])
    pyplot = plt()
    with pyplot.rc_context(FONTS):
        fig = None
        if ax is None:
            fig = pyplot.figure(figsize=(5.5, 3.6), layout="constrained")
            ax = fig.add_subplot()
        ax.plot(pts[ok, 0], pts[ok, 1], "o-", color="C0", ms=4, label="profile (refits)")
        level = f"{100 * profile.level:g} %"
        ax.axhline(profile.threshold, color="k", ls="--", lw=0.8, label=f"χ²₁({level})")
        ends = {"bound": " (bound)", "limit": " (search limit)"}
        lo, hi = profile.lower, profile.upper
        if np.isfinite(lo) and np.isfinite(hi):
            words = ends.get(profile.lower_end, "") + ends.get(profile.upper_end, "")
            ax.axvspan(lo, hi, color=_BAND, zorder=0, label=f"profile interval{words}")
        if np.all(np.isfinite(profile.wald)):
            ax.plot(profile.wald, [profile.threshold] * 2, "|-", color=_OUT, lw=2,
                    ms=12, label="Wald interval")  # fmt: skip
        ax.axvline(profile.estimate, color="0.4", lw=0.8)
        ax.set_xlabel(profile.name)
        ax.set_ylabel("2·(max − profile)")
        ax.set_title(f"profile of {profile.name} ({profile.objective})", loc="left")
        ax.set_ylim(bottom=0.0, top=max(2.5 * profile.threshold, 1.0))
        ax.legend(loc="best")
    if fig is None or path is None:
        return fig if fig is not None else ax.figure
    return save_figure(fig, Path(path))
