"""Residual correlations from any residuals, as MATLAB's ``resid`` computes them.

:func:`residual_correlations` gives, per output, the autocorrelation r(k) of the residuals at lags
k = 0…M and their cross-correlation with each input u_{t−k} at lags k = −M…M, with the pair
counts N_k behind each lag and the pointwise 99 % bands ±2.58/√N_k
(:meth:`Correlations.band`, :meth:`Correlations.cross_band`). NaN marks a missing sample; pairs
are never formed across a trajectory's end. The tests built on them (whiteness, independence from
the inputs, bias) are :func:`ceemx.identification.analysis.diagnostics.residual_diagnostics`; the
figure is :func:`ceemx.evaluation.plots.plot_resid`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike

__all__ = [
    "BAND_Z",
    "Correlations",
    "correlation_statistics",
    "lag_ranges",
    "residual_correlations",
]

#: the pointwise 99 % normal quantile of the correlation bands (±BAND_Z/√N, as ``resid`` draws)
BAND_Z = 2.5758293035489004


class Correlations(NamedTuple):
    """Residual correlations of :func:`residual_correlations`, per output (``m``) and input (``p``).

    Attributes:
        autocorrelation: (m, M + 1) r(k), k = 0…M (r(0) = 1).
        cross_correlation: (m, p, 2M + 1) the correlation of e_t with u_{t−k}, k = −M…M (NaN
            where an input is constant).
        counts: (m,) N, the present samples per output.
        pair_counts: (m, M + 1) N_k, the pairs at each autocorrelation lag.
        cross_pair_counts: (m, p, 2M + 1) the pairs at each cross-correlation lag.
        mean: (m,) the mean residual.
        lags: M.
    """

    autocorrelation: np.ndarray
    cross_correlation: np.ndarray
    counts: np.ndarray
    pair_counts: np.ndarray
    cross_pair_counts: np.ndarray
    mean: np.ndarray
    lags: int

    def band(self, z: float = BAND_Z) -> np.ndarray:
        """(m, M + 1) the pointwise band ±z/√N_k of the autocorrelation (99 % by default)."""
        return z / np.sqrt(np.maximum(self.pair_counts, 1))

    def cross_band(self, z: float = BAND_Z) -> np.ndarray:
        """(m, p, 2M + 1) the pointwise band ±z/√N_k of the cross-correlations."""
        return z / np.sqrt(np.maximum(self.cross_pair_counts, 1))


def _as_btc(values: ArrayLike, name: str) -> np.ndarray:
    """(B, T, c) float64 from (T,), (T, c) or (B, T, c)."""
    a = np.asarray(values, np.float64)
    if a.ndim == 1:
        return a[None, :, None]
    if a.ndim == 2:
        return a[None]
    if a.ndim == 3:
        return a
    raise ValueError(f"`{name}` must be (T,), (T, c) or (B, T, c); got shape {a.shape}.")


def correlation_statistics(
    z: np.ndarray, u: np.ndarray, M: int, inside: np.ndarray | None = None
) -> tuple[Correlations, np.ndarray]:
    """The :class:`Correlations` of (B, T, m) residuals z with (B, T, p) inputs, and mean z².

    NaN in ``z`` marks a missing sample; pairs are never formed across a trajectory's end. The
    mean square is the NIS when ``z`` are standardised prediction errors. ``inside``: (B, T)
    booleans, the steps that belong to a record (``None``: all); the padding of records of
    different lengths is left out of the inputs' mean, spread and pairs. p = 0 (no input) is
    allowed: the cross-correlations are then empty.
    """
    B, T, m = z.shape
    p = u.shape[-1]
    inside = np.ones((B, T), bool) if inside is None else np.asarray(inside, bool)
    acf = np.zeros((m, M + 1))
    pairs = np.zeros((m, M + 1))
    xcf = np.full((m, p, 2 * M + 1), np.nan)
    xpairs = np.zeros((m, p, 2 * M + 1))
    counts = np.zeros(m)
    mean = np.zeros(m)
    nis = np.zeros(m)
    recorded = u[inside]  # (N, p): the inputs of the records, padding left out
    u_mean = recorded.mean(axis=0) if len(recorded) else np.zeros(p)
    us = np.where(inside[..., None], u - u_mean, 0.0)
    u_sd = np.sqrt(np.sum(us**2, axis=(0, 1)) / max(len(recorded), 1))
    for i in range(m):
        present = np.isfinite(z[..., i])
        counts[i] = present.sum()
        if counts[i] == 0:
            acf[i] = np.nan
            nis[i] = mean[i] = np.nan
            continue
        nis[i] = np.nanmean(z[..., i] ** 2)
        mean[i] = np.nanmean(z[..., i])
        c = np.where(present, z[..., i] - mean[i], 0.0)
        var = np.sum(c**2) / counts[i]
        for k in range(M + 1):
            both = present[:, k:] & present[:, : T - k]
            pairs[i, k] = both.sum()
            if pairs[i, k] > 0 and var > 0:
                acf[i, k] = np.sum(c[:, k:] * c[:, : T - k]) / pairs[i, k] / var
        for j in range(p):
            if not u_sd[j] > 0 or not var > 0:
                continue
            for idx, k in enumerate(range(-M, M + 1)):
                # ẽ_t against u_{t−k}
                if k >= 0:
                    zz, uu = c[:, k:], us[:, : T - k, j]
                    pr = present[:, k:] & inside[:, : T - k]
                else:
                    zz, uu = c[:, : T + k], us[:, -k:, j]
                    pr = present[:, : T + k] & inside[:, -k:]
                xpairs[i, j, idx] = pr.sum()
                if xpairs[i, j, idx] > 0:
                    xcf[i, j, idx] = np.sum(zz * uu) / xpairs[i, j, idx] / np.sqrt(var) / u_sd[j]
    return Correlations(acf, xcf, counts, pairs, xpairs, mean, M), nis


def lag_ranges(lags: Sequence[int]) -> str:
    """Lags for a message: ``[1, 2, 3, 7]`` → ``"1–3, 7"``; ``[-5, -4]`` → ``"-5 to -4"``."""
    runs: list[list[int]] = []
    for k in lags:
        if runs and k == runs[-1][-1] + 1:
            runs[-1].append(int(k))
        else:
            runs.append([int(k)])
    sep = lambda a, b: " to " if min(a, b) < 0 else "–"  # noqa: E731
    return ", ".join(f"{r[0]}" if len(r) == 1 else f"{r[0]}{sep(r[0], r[-1])}{r[-1]}" for r in runs)


def residual_correlations(
    residuals: ArrayLike, inputs: ArrayLike | None = None, *, lags: int = 25
) -> Correlations:
    """Autocorrelation of residuals and their cross-correlation with the inputs (MATLAB ``resid``).

    The statistics :func:`~ceemx.identification.analysis.diagnostics.residual_diagnostics` tests,
    from any residuals: one-step prediction errors, free-run simulation errors y − ŷ, whitened CE
    residuals. Pairs are never formed across a trajectory's end; NaN marks a missing sample.

    Args:
        residuals: e, (T,), (T, m) or (B, T, m).
        inputs: u, (T,), (T, p) or (B, T, p) with the same B and T (``None``: no inputs).
        lags: M, the largest lag (capped at T − 1).

    Returns:
        The :class:`Correlations`; ``.band()`` and ``.cross_band()`` give the pointwise 99 %
        bands ±2.58/√N_k that ``resid`` draws.

    Raises:
        ValueError: bad shapes, or ``lags`` < 1.
    """
    e = _as_btc(residuals, "residuals")
    B, T, _ = e.shape
    u = np.zeros((B, T, 0)) if inputs is None else _as_btc(inputs, "inputs")
    if u.shape[:2] != (B, T):
        raise ValueError(
            f"`inputs` must have the residuals' batch and time sizes {(B, T)}; got {u.shape[:2]}."
        )
    if isinstance(lags, bool) or not isinstance(lags, int | np.integer) or lags < 1:
        raise ValueError(f"`lags` must be an integer ≥ 1; got {lags!r}.")
    M = int(min(lags, T - 1))
    c, _ = correlation_statistics(e, u, M)
    return c
