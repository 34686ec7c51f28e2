"""Residual and noise diagnostics of a fitted model, as MATLAB's ``resid`` gives them.

:func:`residual_diagnostics` (and :meth:`ceemx.FitResult.diagnostics`) reads a fitted model on its
data three ways and flags what fails, each flag with a message that says what it means:

1. **Noise ratios** (:mod:`ceemx.identification.analysis.noise_estimate`): the realised / assumed
   variance of every noise component under the Laplace posterior N(x̂, Σ̂) — the expected residual
   second moments E_q[w wᵀ], E_q[v vᵀ], which include the part of the noise the smoothed states
   absorb, so the ratio is ≈ 1 when the assumed noise is consistent (exactly the EM statistic for a
   linear-Gaussian model). One E-step's ratio is biased, though: towards 1 when the assumed noise
   is too *loose* (the posterior spread Σ̂ it adds back is that of the assumed noise), and a too
   tight process noise shows up in the *observation* ratio too (the states cannot follow the
   data). So the noise estimate at the fitted θ is given beside it
   (:func:`~ceemx.identification.analysis.noise_estimate.estimate_noise`: the maximiser of the
   Laplace log-evidence, one factor per noise model) — "assumed 1e-3, the data say 0.095" — and it
   decides the flag: (estimated / assumed std)² outside [1/F, F] (F =
   :data:`~ceemx.identification.analysis.noise_check.FACTOR` = 4; the E-step ratio when
   ``estimate=False``).
2. **One-step prediction errors** of the extended Kalman filter (:func:`ceemx.inference.ekf.ekf`,
   started on each trajectory at the fitted x̂₁ with covariance Q, or the system's
   ``initial_prior``): the innovations e_t = y_t − ŷ_{t|t−1}, standardised per output by their
   predicted standard deviation √S_t,ii (present samples only), pooled over trajectories (never
   across a trajectory's end):

   - NIS, the normalised innovation squared: mean ẽ² per output, ≈ 1 when the filter's predicted
     spread is right (its sampling sd ≈ √(2/N)); flagged outside the band of the end-of-fit ρ,
     [1/2, 4] (too tight or model error above, too loose below; it needs no degrees-of-freedom
     correction);
   - whiteness: the autocorrelation r(k), k = 1…M (M = 25 by default), with the pointwise 99 %
     band ±2.58/√N; flagged when the Box–Pierce statistic Σ_k N_k r(k)² exceeds its χ²_M 99 %
     quantile (one test for all lags: flagging any lag outside a 99 % band would raise a false
     alarm in 1 − 0.99²⁵ = 22 % of correct models);
   - independence from the inputs: the cross-correlation of ẽ_t with each input u_{t−k},
     k = −M…M (k > 0: the input before the error — the model misses how the input acts; k < 0:
     the error before the input — feedback in the data), with the same 99 % band (valid whatever
     the input's own correlation, when ẽ is white); flagged when a lag exceeds the Bonferroni
     bound z_{1−0.005/(2M+1)}/√N_k (1 % for all lags together);
   - bias: the mean of ẽ, flagged beyond 3.29/√N (0.1 %).

   Correlated prediction errors mean the model misses dynamics — or the noise ratio is off: a too
   tight process noise makes the filter sluggish, and its errors correlated at short lags.
3. **The end-of-fit noise check** (:mod:`ceemx.identification.analysis.noise_check`), carried
   over from the fit.

The plot is :func:`ceemx.evaluation.plots.plot_residual_diagnostics` (evaluation reads
identification; never the other way round).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ceemx.data.checks import prepare, promote_tree
from ceemx.data.trajectories import Trajectories
from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.analysis.noise_check import FACTOR, LOWER, NoiseCheck, chi2_band
from ceemx.identification.analysis.noise_estimate import (
    NOISE_FIELDS,
    estimate_noise_prepared,
    moments_prepared,
    noise_ratios,
    start_states,
)
from ceemx.inference.ekf import ekf_prepared
from ceemx.lib.tree import as_jax
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = [
    "BAND_Z",
    "Correlations",
    "ResidualDiagnostics",
    "fit_diagnostics",
    "residual_correlations",
    "residual_diagnostics",
]

#: the pointwise 99 % normal quantile of the correlation bands (±BAND_Z/√N, as ``resid`` draws)
BAND_Z = 2.5758293035489004

_COMPONENT = {"process_noise": "state", "obs_noise": "output"}


@dataclass(frozen=True, eq=False)
class ResidualDiagnostics:
    """The diagnostics of :func:`residual_diagnostics` (module notes).

    Attributes:
        noise_ratios: ``{"process_noise": (n,), "obs_noise": (m,)}`` realised / assumed variance
            under the Laplace posterior at the assumed noise (one E-step; ≈ 1 when consistent,
            biased towards 1 when the noise is too loose).
        assumed_std: the assumed noise standard deviations per component (same keys).
        estimated_std: the noise standard deviations the data say at the fitted θ (same
            keys; ``None`` when not asked for).
        nis: (m,) mean squared standardised one-step prediction error per output.
        bias: (m,) mean standardised prediction error per output.
        autocorrelation: (m, M + 1) r(k), k = 0…M (r(0) = 1), per output.
        cross_correlation: (m, p, 2M + 1) per output and input, lags k = −M…M.
        counts: (m,) N, the present samples per output.
        pair_counts: (m, M + 1) N_k, the pairs at each autocorrelation lag.
        box_pierce: (m,) Σ_k N_k r(k)² over k = 1…M, and ``box_pierce_p`` its χ²_M p-value.
        white: (m,) the whiteness test passed; ``independent`` (m, p) the input test passed;
            ``unbiased`` (m,) the bias test passed (both ``True`` where not run: they need white
            errors); ``nis_ok`` (m,) the NIS is inside its band; ``ratio_ok`` per field: the
            noise is consistent — (estimated / assumed std)² inside [1/F, F] when estimated,
            else the E-step ratio.
        lags: M.
        factor: F of the per-component noise-ratio bands [1/F, F].
        noise_check: the end-of-fit check (``None`` when there was none).
        problems: one message per failed test (empty when all pass).
    """

    noise_ratios: dict
    assumed_std: dict
    estimated_std: dict | None
    nis: np.ndarray
    bias: np.ndarray
    autocorrelation: np.ndarray
    cross_correlation: np.ndarray
    counts: np.ndarray
    pair_counts: np.ndarray
    box_pierce: np.ndarray
    box_pierce_p: np.ndarray
    white: np.ndarray
    independent: np.ndarray
    unbiased: np.ndarray
    nis_ok: np.ndarray
    ratio_ok: dict
    lags: int
    factor: float = FACTOR
    noise_check: NoiseCheck | None = None
    problems: tuple[str, ...] = field(default=())

    @property
    def ok(self) -> bool:
        """Whether every test passed."""
        return not self.problems

    @property
    def band(self) -> np.ndarray:
        """(m,) the pointwise 99 % band ±2.58/√N of the correlations, per output."""
        return BAND_Z / np.sqrt(np.maximum(self.counts, 1))

    def summary(self) -> str:
        """Plain text: a few lines per component, then the problems found."""
        F = self.factor
        lines = ["Residual diagnostics"]
        if self.noise_check is not None:
            lines += self.noise_check.summary().splitlines()
        lines.append(
            f"noise ratios (Laplace E-step, realised / assumed variance; band [{1 / F:.3g}, "
            f"{F:.3g}]; biased towards 1 when the assumed noise is too loose):"
        )
        for name in NOISE_FIELDS:
            ratio, assumed = self.noise_ratios[name], self.assumed_std[name]
            est = None if self.estimated_std is None else self.estimated_std[name]
            for i in range(len(ratio)):
                text = (
                    f"  {name} {_COMPONENT[name]} {i + 1}: ratio {ratio[i]:.3g}  "
                    f"assumed std {assumed[i]:.3g}"
                )
                if est is not None:
                    text += f", the data say {est[i]:.3g}"
                lines.append(text + ("" if self.ratio_ok[name][i] else "  <-- inconsistent"))
        lines.append(f"one-step prediction errors (EKF), lags 1..{self.lags}:")
        for i in range(len(self.nis)):
            tests = (
                [
                    "white",
                    "independent of inputs" if self.independent[i].all() else "input-correlated",
                    "unbiased" if self.unbiased[i] else "biased",
                ]
                if self.white[i]
                else ["NOT white (input and bias tests skipped: they need white errors)"]
            )
            lines.append(
                f"  output {i + 1}: NIS {self.nis[i]:.3g}, mean {self.bias[i]:+.3g}, "
                f"Box-Pierce {self.box_pierce[i]:.3g} (p = {self.box_pierce_p[i]:.2g}); "
                + ", ".join(tests)
            )
        if self.problems:
            lines.append("problems:")
            lines += [f"  - {p}" for p in self.problems]
        else:
            lines.append("no problem found")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"ResidualDiagnostics(outputs={len(self.nis)}, lags={self.lags}, "
            f"problems={len(self.problems)})"
        )


def _lag_ranges(lags: Sequence[int]) -> str:
    """``[1, 2, 3, 7]`` → ``"1–3, 7"``; ``[-5, -4]`` → ``"-5 to -4"``."""
    runs: list[list[int]] = []
    for k in lags:
        if runs and k == runs[-1][-1] + 1:
            runs[-1].append(int(k))
        else:
            runs.append([int(k)])
    sep = lambda a, b: " to " if min(a, b) < 0 else "–"  # noqa: E731
    return ", ".join(f"{r[0]}" if len(r) == 1 else f"{r[0]}{sep(r[0], r[-1])}{r[-1]}" for r in runs)


def _strong(system: AbstractSystem) -> AbstractSystem:
    """Weakly typed leaves (``process_noise=0.1``) made strong: one compiled program for all."""
    return jax.tree_util.tree_map(
        lambda a: jnp.asarray(a, dtype=jnp.result_type(a)) if eqx.is_inexact_array(a) else a,
        system,
    )


def _chi2_sf(x: float, dof: int) -> float:
    from scipy.special import gammaincc

    return float(gammaincc(dof / 2.0, x / 2.0))


def _innovations(system, data, x1, initial):
    """(B, T, m) standardised EKF innovations, NaN where missing (prepared inputs)."""
    B = data.batch_size
    e, s = [], []
    for b in range(B):
        prior = initial
        if prior is None:
            prior = GaussianPrior(jnp.asarray(x1[b]), system.process_noise)
        sol = ekf_prepared(system, data[b : b + 1], promote_tree(prior, system))
        e.append(np.asarray(data.y[b]) - np.asarray(sol.predicted_obs[0]))
        L = np.asarray(sol.innovation_chol[0])
        s.append(np.sqrt(np.sum(L**2, axis=-1)))
    z = np.stack(e) / np.stack(s)
    return np.where(np.asarray(data.mask, bool), z, np.nan)


def _correlations(z: np.ndarray, u: np.ndarray, M: int):
    """Per output: N, pair counts, r(k), cross-correlations with every input (module notes)."""
    B, T, m = z.shape
    p = u.shape[-1]
    acf = np.zeros((m, M + 1))
    pairs = np.zeros((m, M + 1))
    xcf = np.full((m, p, 2 * M + 1), np.nan)
    xpairs = np.zeros((m, p, 2 * M + 1))
    counts = np.zeros(m)
    mean = np.zeros(m)
    nis = np.zeros(m)
    us = u - u.reshape(-1, p).mean(axis=0)
    u_sd = us.reshape(-1, p).std(axis=0)
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
                    zz, uu, pr = c[:, k:], us[:, : T - k, j], present[:, k:]
                else:
                    zz, uu, pr = c[:, : T + k], us[:, -k:, j], present[:, : T + k]
                xpairs[i, j, idx] = pr.sum()
                if xpairs[i, j, idx] > 0:
                    xcf[i, j, idx] = np.sum(zz * uu) / xpairs[i, j, idx] / np.sqrt(var) / u_sd[j]
    return counts, nis, mean, acf, pairs, xcf, xpairs


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
    a = np.asarray(values, np.float64)
    if a.ndim == 1:
        return a[None, :, None]
    if a.ndim == 2:
        return a[None]
    if a.ndim == 3:
        return a
    raise ValueError(f"`{name}` must be (T,), (T, c) or (B, T, c); got shape {a.shape}.")


def residual_correlations(
    residuals: ArrayLike, inputs: ArrayLike | None = None, *, lags: int = 25
) -> Correlations:
    """Autocorrelation of residuals and their cross-correlation with the inputs (MATLAB ``resid``).

    The statistics :func:`residual_diagnostics` tests, from any residuals: one-step prediction
    errors, free-run simulation errors y − ŷ, whitened CE residuals. Pairs are never formed across
    a trajectory's end; NaN marks a missing sample.

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
    p = u.shape[-1]
    if p == 0:  # a constant stand-in (no correlations computed), dropped below
        u = np.zeros((B, T, 1))
    counts, _, mean, acf, pairs, xcf, xpairs = _correlations(e, u, M)
    return Correlations(acf, xcf[:, :p], counts, pairs, xpairs[:, :p], mean, M)


def residual_diagnostics(
    system: AbstractSystem,
    data: Trajectories,
    states: ArrayLike | None = None,
    *,
    lags: int = 25,
    estimate: bool = True,
    factor: float = FACTOR,
    initial: GaussianPrior | None = None,
    noise_check: NoiseCheck | None = None,
) -> ResidualDiagnostics:
    """Noise ratios, the noise estimate and the EKF prediction-error tests (module notes).

    Args:
        system: the (fitted) model; its noise is the assumed noise (Gaussian).
        data: B trajectories (those the model was fitted to, or new ones).
        states: (B, T, n) start states of the MAP smoothing (the fit's states; ``None``: least
            squares through the observation map and a smoothing pass).
        lags: M, the largest correlation lag (capped at T − 1).
        estimate: also estimate the noise at this θ
            (:func:`~ceemx.identification.analysis.noise_estimate.estimate_noise`; a few more
            smoothings).
        factor: F of the per-component noise-ratio bands [1/F, F].
        initial: the EKF's prior on x₁ for every trajectory (``None``: the system's
            ``initial_prior``, else N(x̂₁, Q) at each trajectory's MAP x̂₁).
        noise_check: the fit's end-of-fit check, carried into the report.

    Returns:
        A :class:`ResidualDiagnostics`; ``.summary()`` prints it, ``.problems`` lists what failed.

    Raises:
        TypeError: a noise model is not Gaussian (the EKF and the noise ratios need Gaussian
            noise).
        ValueError: ``lags`` < 1 or ``factor`` ≤ 1.
    """
    for name in NOISE_FIELDS:
        if not getattr(system, name).is_gaussian:
            raise TypeError(
                f"residual diagnostics need Gaussian noise; system.{name} is "
                f"{type(getattr(system, name)).__name__}."
            )
    if isinstance(lags, bool) or not isinstance(lags, int | np.integer) or lags < 1:
        raise ValueError(f"`lags` must be an integer ≥ 1; got {lags!r}.")
    if not (np.isfinite(factor) and factor > 1):
        raise ValueError(f"`factor` must be finite and > 1; got {factor!r}.")
    M = int(min(lags, data.num_steps - 1))
    system = _strong(system)
    inputs = prepare(system, data, states, identify=True)
    problems: list[str] = []
    nm = moments_prepared(inputs.system, inputs.data, start_states(inputs))
    ok = np.asarray(nm.ok)
    assumed = {name: _std(getattr(system, name)) for name in NOISE_FIELDS}
    estimated = None
    if ok.any():
        ratios = noise_ratios(system, nm)
        if estimate:
            fitted, _, _ = estimate_noise_prepared(system, inputs.data, nm.states)
            estimated = {name: _std(getattr(fitted, name)) for name in NOISE_FIELDS}
    else:
        ratios = {name: np.full(len(assumed[name]), np.nan) for name in NOISE_FIELDS}
    if not ok.all():
        problems.append(
            f"the Laplace posterior is not finite for trajectories {np.flatnonzero(~ok).tolist()}"
            " (a state neither observed nor pinned by a prior on x₁ makes the Gauss–Newton "
            "matrix singular): they are left out of the noise ratios."
        )
    if initial is None:
        initial = system.initial_prior
    x1 = np.asarray(nm.states[:, 0])
    if states is not None:  # where the MAP failed, the given start
        x1 = np.where(np.isfinite(x1), x1, np.asarray(states)[:, 0])
    z = _innovations(inputs.system, inputs.data, x1, initial)
    counts, nis, mean, acf, pairs, xcf, xpairs = _correlations(z, np.asarray(data.u), M)

    ratio_ok = {}
    for name in NOISE_FIELDS:
        # The verdict: the evidence maximiser when estimated (unbiased either way), else the E-step.
        r = ratios[name] if estimated is None else (estimated[name] / assumed[name]) ** 2
        ok = ~np.isfinite(r) | ((r >= 1.0 / factor) & (r <= factor))
        ratio_ok[name] = ok
        for i in np.flatnonzero(~ok):
            way = "too tight (or the model misses dynamics)" if r[i] > 1 else "too loose"
            text = f"{name} ({_COMPONENT[name]} {i + 1}): assumed std {assumed[name][i]:.3g}"
            if estimated is not None:
                text += (
                    f", the data say {estimated[name][i]:.3g} (estimate_noise at the fitted θ; "
                    f"one E-step's variance ratio {ratios[name][i]:.3g})"
                )
            else:
                text += f": the realised variance is {r[i]:.3g}× the assumed (Laplace E-step)"
            problems.append(f"{text}: the assumed noise is {way}.")

    nis_ok = np.ones(len(nis), bool)
    white = np.ones(len(nis), bool)
    unbiased = np.ones(len(nis), bool)
    independent = np.ones(xcf.shape[:2], bool)
    box = np.full(len(nis), np.nan)
    box_p = np.full(len(nis), np.nan)
    z_bonf = NormalDist().inv_cdf(1.0 - 0.005 / (2 * M + 1))
    z_bias = NormalDist().inv_cdf(1.0 - 0.0005)
    for i in range(len(nis)):
        N = counts[i]
        if N < 2:
            continue
        lo, hi = chi2_band(N)
        nis_lo, nis_hi = min(LOWER, lo), max(FACTOR, hi)
        if not nis_lo <= nis[i] <= nis_hi:
            nis_ok[i] = False
            way = "too tight (or the model misses dynamics)" if nis[i] > 1 else "too loose"
            problems.append(
                f"output {i + 1}: the one-step prediction errors are {nis[i]:.3g}× their "
                f"predicted variance (NIS; {np.sqrt(nis[i]):.3g}× in std): the assumed noise is "
                f"{way}."
            )
        box[i] = float(np.sum(pairs[i, 1:] * acf[i, 1:] ** 2))
        box_p[i] = _chi2_sf(box[i], M)
        if box_p[i] < 0.01:
            white[i] = False
            band = BAND_Z / np.sqrt(np.maximum(pairs[i, 1:], 1))
            out = [k for k in range(1, M + 1) if abs(acf[i, k]) > band[k - 1]]
            where = f"at lags {_lag_ranges(out)}" if out else "over lags 1–" + str(M)
            problems.append(
                f"output {i + 1}: the one-step prediction errors are correlated {where} "
                f"(Box–Pierce p = {box_p[i]:.2g}): the model misses dynamics, or the noise "
                "ratio is off (a too tight process noise makes the filter sluggish)."
            )
        if not white[i]:
            continue  # the bias and input tests assume white errors (their bands do)
        if abs(mean[i]) * np.sqrt(N) > z_bias:
            unbiased[i] = False
            problems.append(
                f"output {i + 1}: the one-step prediction errors have mean {mean[i]:+.3g} "
                "(in predicted standard deviations): the model misses an offset."
            )
        for j in range(xcf.shape[1]):
            row = xcf[i, j]
            if not np.isfinite(row).any():
                continue
            scaled = np.abs(row) * np.sqrt(np.maximum(xpairs[i, j], 1))
            if np.nanmax(scaled) > z_bonf:
                independent[i, j] = False
                ks = np.arange(-M, M + 1)
                band = BAND_Z / np.sqrt(np.maximum(xpairs[i, j], 1))
                out = ks[np.abs(row) > band]
                pos = [int(k) for k in out if k >= 0]
                neg = [int(k) for k in out if k < 0]
                text = (
                    f"output {i + 1}: the one-step prediction errors correlate with input {j + 1}"
                )
                if pos:
                    text += (
                        f" at lags {_lag_ranges(pos)} (input before error): the model misses "
                        "how the input acts (input dynamics, delay or feedthrough)"
                    )
                if neg:
                    text += (
                        f"{';' if pos else ''} at lags {_lag_ranges(neg)} (error before input): "
                        "feedback in the data"
                    )
                problems.append(text + ".")
    return ResidualDiagnostics(
        noise_ratios=ratios,
        assumed_std=assumed,
        estimated_std=estimated,
        nis=nis,
        bias=mean,
        autocorrelation=acf,
        cross_correlation=xcf,
        counts=counts,
        pair_counts=pairs,
        box_pierce=box,
        box_pierce_p=box_p,
        white=white,
        independent=independent,
        unbiased=unbiased,
        nis_ok=nis_ok,
        ratio_ok=ratio_ok,
        lags=M,
        factor=factor,
        noise_check=noise_check,
        problems=tuple(problems),
    )


def _std(noise) -> np.ndarray:
    return np.sqrt(np.diagonal(np.asarray(noise.covariance(), np.float64)))


def fit_diagnostics(result: Any, **options) -> ResidualDiagnostics:
    """:meth:`ceemx.FitResult.diagnostics`: :func:`residual_diagnostics` at the fit's end point."""
    problem, _, states, weights = end_point(result)
    keep = np.flatnonzero(np.asarray(weights) > 0)
    data = problem.data[keep] if keep.size < states.shape[0] else problem.data
    states = states[as_jax(keep)] if keep.size < states.shape[0] else states
    return residual_diagnostics(
        result.system, data, states, noise_check=result.noise_check, **options
    )
