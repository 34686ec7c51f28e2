"""The panels of :func:`ceemx.evaluation.plots.plot_benchmark`: one record's traces, readable.

Each row of the figure is a panel over the whole record and, beside it, one over the zoomed
window (:class:`TracePanels` shades the initial-state window grey and marks the zoomed window
yellow on the whole-record panels). Over the whole record a long record is drawn as the band
between each bin's minimum and maximum (:func:`envelope`: exact, and a small file); the zoomed
window shows every sample.

- :func:`draw_outputs` — per output, the measured output and each model's simulation (legend: its
  RMSE), then the simulation error y − ŷ on its own axis (scaled to the best model);
- :func:`draw_hidden` — one hidden state with its label and physical bounds, and a note when it
  leaves them;
- :func:`label_time_axes` — the time axis on the last row only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "Bounds",
    "TracePanels",
    "axes_grid",
    "draw_hidden",
    "draw_outputs",
    "envelope",
    "label_time_axes",
    "rmse",
    "zoom_window",
]

#: A hidden state's physical range (low, high), ``None`` for an open side; ``None``: no range.
Bounds = tuple[float | None, float | None] | None

_MEASURED = "0.15"
_OUT = "#d62728"
_ZOOM = "#fff3b0"
_INIT = "0.88"


def envelope(x: np.ndarray, v: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The min and max of v over each of ``bins`` bins, at the bins' first x (display only)."""
    starts = np.linspace(0, v.shape[0], max(bins, 2) + 1).astype(int)[:-1]
    with np.errstate(invalid="ignore"):
        lo, hi = np.fmin.reduceat(v, starts), np.fmax.reduceat(v, starts)
    return np.append(x[starts], x[-1]), np.append(lo, lo[-1]), np.append(hi, hi[-1])


def zoom_window(
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


def rmse(y: np.ndarray, y_sim: np.ndarray, n_init: int) -> np.ndarray:
    """(m,) RMSE over samples n_init: where both are finite."""
    d = (y_sim - y)[n_init:]
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.nanmean(np.where(np.isfinite(d), d, np.nan) ** 2, axis=0))


def _fmt_unit(unit: str) -> str:
    return f" [{unit}]" if unit else ""


def axes_grid(fig, heights: list[float], zoomed: bool):
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


@dataclass(frozen=True)
class TracePanels:
    """The x-axis every row shares: sample times, the initial-state window, the zoomed window.

    Attributes:
        x: (T,) the sample times (sample indices, or seconds).
        n_init: samples of the initial-state window (shaded grey).
        window: [a, b) of the zoomed panels (``None``: no zoomed column).
        max_points: above this many samples the whole-record panels draw the min/max band.
        in_samples: whether x counts samples (else seconds).
    """

    x: np.ndarray
    n_init: int
    window: tuple[int, int] | None
    max_points: int
    in_samples: bool

    def columns(self, row) -> list[tuple[bool, Any]]:
        """(zoomed, axes) of a row's panels: the whole record, then the zoom when there is one."""
        return [
            (zoomed, ax) for zoomed, ax in zip((False, True), row, strict=True) if ax is not None
        ]

    def shade(self, ax, zoomed: bool) -> None:
        """The x-limits, the initial-state window and (whole record) the zoomed window."""
        x, n_init = self.x, self.n_init
        if zoomed:
            assert self.window is not None
            a, b = self.window
            if n_init > a:
                ax.axvspan(x[a], x[min(n_init, b - 1)], color=_INIT, lw=0, zorder=0)
            ax.set_xlim(x[a], x[b - 1])
            return
        if n_init > 0:
            ax.axvspan(x[0], x[n_init], color=_INIT, lw=0, zorder=0)
        if self.window is not None:
            ax.axvspan(x[self.window[0]], x[self.window[1] - 1], color=_ZOOM, lw=0, zorder=0)
        ax.set_xlim(x[0], x[-1])

    def draw(self, ax, v: np.ndarray, zoomed: bool, **kw):
        """Draw v (a line, or the min/max band of a long record); returns its legend handle."""
        x = self.x
        if zoomed:
            assert self.window is not None
            sl = slice(*self.window)
            return ax.plot(x[sl], v[sl], **kw)[0]
        T = x.shape[0]
        if T <= self.max_points:
            lw_full = 0.5 if T > 2000 else 0.9
            return ax.plot(x, v, **{**kw, "lw": kw["lw"] * (lw_full / 0.9)})[0]
        from matplotlib.lines import Line2D

        # A long record: the band between each bin's min and max (exact envelope, a small
        # file); a line stands for it in the legend.
        xb, lo, hi = envelope(x, v, self.max_points // 2)
        ax.fill_between(xb, lo, hi, step="post", color=kw["color"], lw=0, zorder=kw["zorder"])
        return Line2D([], [], color=kw["color"], lw=kw["lw"])

    def zoom_title(self, ax) -> None:
        """The zoomed window's span, over its panel."""
        assert self.window is not None
        a, b = self.window
        x = self.x
        span = f"samples {a}–{b - 1}" if self.in_samples else f"{x[a]:.4g}–{x[b - 1]:.4g} s"
        ax.set_title(f"zoom: {span}", loc="left")


def _scores(y: np.ndarray, sims: Mapping[str, np.ndarray], n_init: int):
    """Each model's RMSE on y[n_init:], and the models in drawing order (the best last)."""
    score = {n: rmse(y[:, None], s[:, None], n_init)[0] for n, s in sims.items()}
    order = sorted(sims, key=lambda n: -score[n] if np.isfinite(score[n]) else -np.inf)
    return score, order


def _error_limit(err: np.ndarray, n_init: int, spread: float) -> float:
    """The error axis' half-height: the best model's largest error, capped at the output's range."""
    with np.errstate(invalid="ignore"):
        e_lim = float(np.nanmax(np.abs(err[n_init:]), initial=0.0))
    return 1.1 * min(e_lim if np.isfinite(e_lim) else np.inf, spread) + 1e-12


def _output_row(panels: TracePanels, row, y: np.ndarray, sims, order, colors) -> dict[str, Any]:
    """The measured output and each model's simulation; returns the whole record's handles."""
    lo, hi = np.nanmin(y), np.nanmax(y)
    pad = 0.12 * (hi - lo) + 1e-12
    handles: dict[str, Any] = {}
    for zoomed, ax in panels.columns(row):
        panels.shade(ax, zoomed)
        lines = {"": panels.draw(ax, y, zoomed, color=_MEASURED, lw=1.7, zorder=2)}
        for name in order:  # the best model last, on top
            lines[name] = panels.draw(ax, sims[name], zoomed, color=colors[name], lw=1.0, zorder=3)
        if not zoomed:
            handles = lines
        ax.set_ylim(lo - pad, hi + pad)
    return handles


def _error_row(panels: TracePanels, row, errs, order, colors, limit: float) -> None:
    """Each model's simulation error y − ŷ on an axis of half-height ``limit``."""
    for zoomed, ax in panels.columns(row):
        panels.shade(ax, zoomed)
        ax.axhline(0.0, color="0.5", lw=0.6)
        for name in order:
            panels.draw(ax, errs[name], zoomed, color=colors[name], lw=1.0, zorder=2)
        ax.set_ylim(-limit, limit)


def _output_legend(ax, handles, labels: list[str], n_init: int) -> None:
    """The legend above the output panel (a legend inside would hide data, one beside squash it)."""
    from matplotlib.patches import Patch

    if n_init > 0:
        handles.append(Patch(color=_INIT))
        labels.append(f"initial-state window (n_init = {n_init})")
    leg = ax.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.0, 1.0),
                    ncols=2, frameon=False, borderaxespad=0.2)  # fmt: skip
    for line in leg.get_lines():
        line.set_linewidth(2.0)


def draw_outputs(
    panels: TracePanels,
    rows,
    y: np.ndarray,
    sims: Mapping[str, np.ndarray],
    *,
    names: Sequence[str],
    unit: str,
    score_unit: str,
    score_scale: float,
) -> None:
    """Per output j, rows 2j (measured and simulated) and 2j + 1 (the errors) of ``rows``.

    The error axis follows the best model (drawn last, on top), capped at the output's range;
    axis limits follow the measured output, so a diverging model cannot squash the data (its
    legend entry still gives its RMSE, times ``score_scale`` in ``score_unit``).
    """
    colors = {name: f"C{i}" for i, name in enumerate(sims)}
    for j in range(y.shape[1]):
        row_y, row_e = rows[2 * j], rows[2 * j + 1]
        yj = y[:, j]
        sj = {name: s[:, j] for name, s in sims.items()}
        errs = {name: yj - s for name, s in sj.items()}
        score, order = _scores(yj, sj, panels.n_init)
        limit = _error_limit(errs[order[-1]], panels.n_init, float(np.nanmax(yj) - np.nanmin(yj)))
        lines = _output_row(panels, row_y, yj, sj, order, colors)
        _error_row(panels, row_e, errs, order, colors, limit)
        row_y[0].set_ylabel(f"{names[j]}{_fmt_unit(unit)}")
        row_e[0].set_ylabel(f"error y − ŷ{_fmt_unit(unit)}")
        labels = ["measured"] + [
            f"{n} (RMSE {score[n] * score_scale:.3g}{' ' + score_unit if score_unit else ''})"
            for n in sims
        ]
        _output_legend(row_y[0], [lines[""]] + [lines[n] for n in sims], labels, panels.n_init)
        if row_y[1] is not None:
            panels.zoom_title(row_y[1])


def _bounds_note(v: np.ndarray, bounds: Bounds) -> str:
    """How often and how far v leaves its bounds ("" when it never does)."""
    if bounds is None:
        return ""
    low = -np.inf if bounds[0] is None else float(bounds[0])
    high = np.inf if bounds[1] is None else float(bounds[1])
    with np.errstate(invalid="ignore"):
        outside = (v < low) | (v > high)
    if not outside.any():
        return ""
    worst = np.nanmin(v) if np.nanmin(v) < low else np.nanmax(v)
    return f"outside on {100 * outside.mean():.0f} % of samples (reaches {worst:.3g})"


def _draw_bounds(ax, v: np.ndarray, bounds: Bounds) -> None:
    """The bounds dashed, the region outside them shaded; y-limits that show both."""
    edges = [] if bounds is None else [e for e in bounds if e is not None]
    if bounds is None or not edges:
        return
    vmin, vmax = np.nanmin(v), np.nanmax(v)
    span = max(vmax, *edges) - min(vmin, *edges) + 1e-12
    ylo, yhi = min(vmin, *edges) - 0.08 * span, max(vmax, *edges) + 0.08 * span
    for edge, other in ((bounds[0], ylo), (bounds[1], yhi)):
        if edge is None:
            continue
        ax.axhline(edge, color=_OUT, lw=0.9, ls="--", zorder=1)
        ax.axhspan(edge, other, color=_OUT, alpha=0.08, lw=0, zorder=0)
    ax.set_ylim(ylo, yhi)


def draw_hidden(panels: TracePanels, row, v: np.ndarray, label: str, bounds: Bounds) -> None:
    """One hidden state: its trace, label and physical range (and a note when it leaves it)."""
    note = _bounds_note(v, bounds)
    for zoomed, ax in panels.columns(row):
        panels.shade(ax, zoomed)
        panels.draw(ax, v, zoomed, color="C0", lw=1.1, zorder=2)
        _draw_bounds(ax, v, bounds)
    text = label
    if bounds is not None:
        rng = ", ".join("—" if e is None else f"{e:.3g}" for e in bounds)
        text += f" — physical range [{rng}]"
    row[0].set_title(text, loc="left")
    if note:  # the model leaves the physical range: say so where it is seen
        row[0].set_title(note, loc="right", color=_OUT)


def label_time_axes(rows, xlabel: str) -> None:
    """The time axis' label on the last row, no tick labels above it (the columns share x)."""
    for full, zoom_ax in rows[-1:]:
        full.set_xlabel(xlabel)
        if zoom_ax is not None:
            zoom_ax.set_xlabel(xlabel)
    for full, zoom_ax in rows[:-1]:
        full.tick_params(labelbottom=False)
        if zoom_ax is not None:
            zoom_ax.tick_params(labelbottom=False)
