"""Figures a person can read: benchmark traces and residual correlations, from plain arrays.

- :func:`plot_benchmark` — measured and simulated outputs of one record (one or several models)
  over the whole record and, beside it, a zoomed window; the simulation error y − ŷ on its own
  axis below; optionally hidden states with their physical meaning and bounds (and a note when a
  state leaves them).
- :func:`plot_resid` — the autocorrelation of residuals and their cross-correlation with each
  input, with the pointwise 99 % band ±2.58/√N, as MATLAB's ``resid`` draws them (the numbers:
  :func:`ceemx.identification.analysis.diagnostics.residual_correlations`).
- :func:`plot_residual_diagnostics` — the figure of :meth:`ceemx.FitResult.diagnostics`.

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
from typing import Any

import numpy as np
from jaxtyping import ArrayLike

from ceemx.evaluation.report import plt, save_figure
from ceemx.identification.analysis.diagnostics import BAND_Z, residual_correlations

__all__ = ["FONTS", "plot_benchmark", "plot_resid", "plot_residual_diagnostics"]

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

_MEASURED = "0.15"
_BAND = "#c6dbef"
_OUT = "#d62728"
_ZOOM = "#fff3b0"
_INIT = "0.88"


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


def _envelope(x: np.ndarray, v: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The min and max of v over each of ``bins`` bins, at the bins' first x (display only)."""
    starts = np.linspace(0, v.shape[0], max(bins, 2) + 1).astype(int)[:-1]
    with np.errstate(invalid="ignore"):
        lo, hi = np.fmin.reduceat(v, starts), np.fmax.reduceat(v, starts)
    return np.append(x[starts], x[-1]), np.append(lo, lo[-1]), np.append(hi, hi[-1])


def _zoom_window(
    zoom: Any, err: np.ndarray, n_init: int, T: int, fraction: float, max_samples: int
) -> tuple[int, int] | None:
    """[a, b) of the zoomed panel: given, around the largest error, or from the start."""
    if zoom is False:
        return None
    if isinstance(zoom, tuple | list):
        a, b = (int(z) for z in zoom)
        if not 0 <= a < b <= T:
            raise ValueError(
                f"`zoom` must be (start, stop) with 0 ≤ start < stop ≤ {T}; got {zoom}."
            )
        return a, b
    if zoom not in (None, "error", "start"):
        raise ValueError(f"`zoom` must be 'error', 'start', (start, stop) or False; got {zoom!r}.")
    L = min(T, max(int(round(fraction * T)), 20), max_samples)
    if zoom == "start":
        a = max(0, n_init - L // 10)
    else:
        tail = np.abs(err[n_init:])
        if tail.size == 0 or not np.isfinite(tail).any():
            a = max(0, n_init - L // 10)
        else:
            centre = n_init + int(np.nanargmax(np.nanmax(tail, axis=-1)))
            a = centre - L // 2
    a = min(max(a, 0), T - L)
    return a, a + L


def _rmse(y: np.ndarray, y_sim: np.ndarray, n_init: int) -> np.ndarray:
    """(m,) RMSE over samples n_init: where both are finite."""
    d = (y_sim - y)[n_init:]
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.nanmean(np.where(np.isfinite(d), d, np.nan) ** 2, axis=0))


def _fmt_unit(unit: str) -> str:
    return f" [{unit}]" if unit else ""


def _axes_grid(fig, heights: list[float], zoomed: bool):
    """Rows of (full, zoom) axes; the full column shares x, so does the zoom column."""
    cols = 2 if zoomed else 1
    grid = fig.add_gridspec(len(heights), cols, height_ratios=heights, width_ratios=[3.2, 1][:cols])
    rows = []
    first_full = first_zoom = None
    for r in range(len(heights)):
        full = fig.add_subplot(grid[r, 0], sharex=first_full)
        first_full = first_full or full
        zoom = None
        if zoomed:
            zoom = fig.add_subplot(grid[r, 1], sharex=first_zoom)
            first_zoom = first_zoom or zoom
        rows.append((full, zoom))
    return rows


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

    Rows, each a panel over the whole record (left) and the zoomed window (right): per output,
    the measured output (black) and each model's free-run simulation (legend: its RMSE on
    samples ``n_init:``), then the simulation error y − ŷ of each model on its own axis; then,
    when given, one row per hidden state with its label and physical bounds (dashed, the region
    outside shaded; a note gives how often and how far the state leaves them). The first
    ``n_init`` samples (the initial-state window, not scored) are shaded grey; the zoomed window
    is marked yellow on the whole-record panels. Axis limits follow the measured output, so a
    diverging model cannot squash the data (its legend entry still gives its RMSE).

    Args:
        y: the measured output of one record: (T,), (T, m) or (1, T, m) (NaN: missing).
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
        max_points: above this many samples the whole-record panels draw the band between each
            of ``max_points / 2`` bins' minimum and maximum (display only).
        fig: a ``Figure`` or ``SubFigure`` to draw into (default: a new figure, constrained layout,
            11 in wide).

    Returns:
        The figure (``report.save_figure(fig, path)`` writes and closes it).

    Raises:
        ValueError: shapes that do not match, or a bad ``zoom``, ``n_init`` or name count.

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
    yy = _as_tm(y, "y")
    T, m = yy.shape
    sims_in = dict(y_sim) if isinstance(y_sim, Mapping) else {label: y_sim}
    if not sims_in:
        raise ValueError("`y_sim` is empty: give at least one simulation.")
    sims = {}
    for name, s in sims_in.items():
        s = _as_tm(s, f"y_sim[{name!r}]")
        if s.shape != yy.shape:
            raise ValueError(f"y_sim[{name!r}] has shape {s.shape}; y has {yy.shape}.")
        sims[name] = s
    n_init = int(n_init)
    if not 0 <= n_init < T:
        raise ValueError(f"`n_init` must be in [0, {T}); got {n_init}.")
    out_names = _names(output_names, m, "y", "output_names")
    hid = None if hidden is None else _as_tm(hidden, "hidden")
    if hid is not None and hid.shape[0] != T:
        raise ValueError(f"`hidden` has {hid.shape[0]} samples; y has {T}.")
    k = 0 if hid is None else hid.shape[1]
    hid_names = _names(hidden_label, k, "hidden state", "hidden_label") if k else []
    hid_bounds: list[tuple[float | None, float | None] | None] = [None] * k
    if bounds is not None and k:
        pair = len(bounds) == 2 and all(b is None or np.isscalar(b) for b in bounds)
        given = [bounds] if pair else list(bounds)
        if len(given) != k:
            raise ValueError(f"`bounds` needs {k} (low, high) pairs; got {len(given)}.")
        hid_bounds = [None if b is None else (b[0], b[1]) for b in given]  # type: ignore[index]
    s_unit = unit if score_unit is None else score_unit

    first = next(iter(sims.values()))
    window = _zoom_window(zoom, yy - first, n_init, T, zoom_fraction, int(zoom_samples))
    x = np.arange(T) * (1.0 if dt is None else float(dt))
    xlabel = "sample" if dt is None else "time [s]"
    heights = [2.3, 1.3] * m + [1.5] * k
    pyplot = plt()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    with pyplot.rc_context(FONTS):
        fig = _new_figure(fig, (11.0, 0.9 + 1.25 * sum(heights)))
        rows = _axes_grid(fig, heights, window is not None)
        lw_full = 0.5 if T > 2000 else 0.9
        colors = {name: f"C{i}" for i, name in enumerate(sims)}

        def shade(ax, zoomed: bool):
            if zoomed:
                assert window is not None
                a, b = window
                if n_init > a:
                    ax.axvspan(x[a], x[min(n_init, b - 1)], color=_INIT, lw=0, zorder=0)
                ax.set_xlim(x[a], x[b - 1])
                return
            if n_init > 0:
                ax.axvspan(x[0], x[n_init], color=_INIT, lw=0, zorder=0)
            if window is not None:
                ax.axvspan(x[window[0]], x[window[1] - 1], color=_ZOOM, lw=0, zorder=0)
            ax.set_xlim(x[0], x[-1])

        def draw(ax, v, zoomed, **kw):
            if zoomed:
                assert window is not None
                sl = slice(*window)
                return ax.plot(x[sl], v[sl], **kw)[0]
            if T <= max_points:
                return ax.plot(x, v, **{**kw, "lw": kw["lw"] * (lw_full / 0.9)})[0]
            # A long record: the band between each bin's min and max (exact envelope, a small
            # file); a line stands for it in the legend.
            xb, lo, hi = _envelope(x, v, max_points // 2)
            ax.fill_between(xb, lo, hi, step="post", color=kw["color"], lw=0, zorder=kw["zorder"])
            return Line2D([], [], color=kw["color"], lw=kw["lw"])

        for j in range(m):
            ax_y, ax_e = rows[2 * j], rows[2 * j + 1]
            lo, hi = np.nanmin(yy[:, j]), np.nanmax(yy[:, j])
            pad = 0.12 * (hi - lo) + 1e-12
            errs = {name: yy[:, j] - s[:, j] for name, s in sims.items()}
            # The error axis follows the best model (drawn last, on top), capped at the output's
            # range.
            score = {
                n: _rmse(yy[:, j : j + 1], s[:, j : j + 1], n_init)[0] for n, s in sims.items()
            }
            order = sorted(errs, key=lambda n: -score[n] if np.isfinite(score[n]) else -np.inf)
            best = order[-1]
            with np.errstate(invalid="ignore"):
                e_lim = float(np.nanmax(np.abs(errs[best][n_init:]), initial=0.0))
            e_lim = 1.1 * min(e_lim if np.isfinite(e_lim) else np.inf, float(hi - lo)) + 1e-12
            handles, labels = [], []
            for zoomed, ax in ((False, ax_y[0]), (True, ax_y[1])):
                if ax is None:
                    continue
                shade(ax, zoomed)
                lines = {"": draw(ax, yy[:, j], zoomed, color=_MEASURED, lw=1.7, zorder=2)}
                for name in order:  # the best model last, on top
                    lines[name] = draw(ax, sims[name][:, j], zoomed, color=colors[name], lw=1.0,
                                       zorder=3)  # fmt: skip
                if not zoomed:
                    handles = [lines[""]] + [lines[n] for n in sims]
                    labels = ["measured"] + [
                        f"{n} (RMSE {score[n] * score_scale:.3g}{' ' + s_unit if s_unit else ''})"
                        for n in sims
                    ]
                ax.set_ylim(lo - pad, hi + pad)
            for zoomed, ax in ((False, ax_e[0]), (True, ax_e[1])):
                if ax is None:
                    continue
                shade(ax, zoomed)
                ax.axhline(0.0, color="0.5", lw=0.6)
                for name in order:
                    draw(ax, errs[name], zoomed, color=colors[name], lw=1.0, zorder=2)
                ax.set_ylim(-e_lim, e_lim)
            ax_y[0].set_ylabel(f"{out_names[j]}{_fmt_unit(unit)}")
            ax_e[0].set_ylabel(f"error y − ŷ{_fmt_unit(unit)}")
            if n_init > 0:
                handles.append(Patch(color=_INIT))
                labels.append(f"initial-state window (n_init = {n_init})")
            # Above the panel (a legend inside would hide data, one beside would squash it).
            leg = ax_y[0].legend(handles, labels, loc="lower left", bbox_to_anchor=(0.0, 1.0),
                                 ncols=2, frameon=False, borderaxespad=0.2)  # fmt: skip
            for line in leg.get_lines():
                line.set_linewidth(2.0)
            if ax_y[1] is not None:
                assert window is not None
                a, b = window
                span = f"samples {a}–{b - 1}" if dt is None else f"{x[a]:.4g}–{x[b - 1]:.4g} s"
                ax_y[1].set_title(f"zoom: {span}", loc="left")

        for i in range(k):
            ax_full, ax_zoom = rows[2 * m + i]
            v = hid[:, i]  # type: ignore[index]
            b = hid_bounds[i]
            note = ""
            if b is not None:
                low = -np.inf if b[0] is None else float(b[0])
                high = np.inf if b[1] is None else float(b[1])
                with np.errstate(invalid="ignore"):
                    outside = (v < low) | (v > high)
                if outside.any():
                    worst = np.nanmin(v) if np.nanmin(v) < low else np.nanmax(v)
                    note = (
                        f"outside on {100 * outside.mean():.0f} % of samples (reaches {worst:.3g})"
                    )
            for zoomed, ax in ((False, ax_full), (True, ax_zoom)):
                if ax is None:
                    continue
                shade(ax, zoomed)
                draw(ax, v, zoomed, color="C0", lw=1.1, zorder=2)
                edges = [] if b is None else [e for e in b if e is not None]
                if b is not None and edges:
                    vmin, vmax = np.nanmin(v), np.nanmax(v)
                    span = max(vmax, *edges) - min(vmin, *edges) + 1e-12
                    ylo, yhi = min(vmin, *edges) - 0.08 * span, max(vmax, *edges) + 0.08 * span
                    for edge, other in ((b[0], ylo), (b[1], yhi)):
                        if edge is None:
                            continue
                        ax.axhline(edge, color=_OUT, lw=0.9, ls="--", zorder=1)
                        ax.axhspan(edge, other, color=_OUT, alpha=0.08, lw=0, zorder=0)
                    ax.set_ylim(ylo, yhi)
            text = hid_names[i]
            if b is not None:
                rng = ", ".join("—" if e is None else f"{e:.3g}" for e in b)
                text += f" — physical range [{rng}]"
            ax_full.set_title(text, loc="left")
            if note:  # the model leaves the physical range: say so where it is seen
                ax_full.set_title(note, loc="right", color=_OUT)
        for full, zoom_ax in rows[-1:]:
            full.set_xlabel(xlabel)
            if zoom_ax is not None:
                zoom_ax.set_xlabel(xlabel)
        for full, zoom_ax in rows[:-1]:
            full.tick_params(labelbottom=False)
            if zoom_ax is not None:
                zoom_ax.tick_params(labelbottom=False)
        if title:
            fig.suptitle(title, x=0.01, ha="left", fontweight="bold")
    return fig


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
            verdict = "white" if diag.white[i] else "NOT white"
            _correlation_axis(ax, np.arange(1, M + 1), acf[i, 1:], band[i, 1:],
                              f"output {i + 1}: autocorrelation ({verdict}; NIS {diag.nis[i]:.3g})",
                              "lag k", legend=i == 0)  # fmt: skip
            for j in range(p):
                ax = fig.add_subplot(grid[i, 1 + j])
                xb = BAND_Z / math.sqrt(max(float(diag.counts[i]), 1.0))
                ok = "independent" if diag.independent[i, j] else "CORRELATED"
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
