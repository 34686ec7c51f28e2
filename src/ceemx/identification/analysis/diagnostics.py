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
   - bias: the mean of ẽ, flagged beyond 3.29/√N (0.1 %);
   - outliers: the largest |ẽ| of each output, flagged when a Gaussian error that large among N
     is improbable: its Bonferroni p-value N·P(|Z| ≥ max|ẽ|) below 1 % (≈ 4.3 predicted standard
     deviations at N = 500). One glitch in a record (a sensor spike) passes the variance and
     whiteness tests once a learned noise has absorbed it — σ_v learned 400× the true value
     from one sample 10⁴ noise standard deviations off — but stands out here: its error is still
     ≈ √N of the inflated noise's.

   Correlated prediction errors mean the model misses dynamics — or the noise ratio is off: a too
   tight process noise makes the filter sluggish, and its errors correlated at short lags.
3. **The end-of-fit noise check** (:mod:`ceemx.identification.analysis.noise_check`), carried
   over from the fit.

The plot is :func:`ceemx.evaluation.plots.plot_residual_diagnostics` (evaluation reads
identification; never the other way round).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ceemx.data.arrays import indexed
from ceemx.data.checks import Prepared, prepare, promote_tree
from ceemx.data.trajectories import Trajectories
from ceemx.identification.analysis.correlations import (
    BAND_Z,
    Correlations,
    correlation_statistics,
    lag_ranges,
)
from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.analysis.noise_check import FACTOR, LOWER, NoiseCheck, chi2_band
from ceemx.identification.analysis.noise_estimate import (
    NOISE_FIELDS,
    NoiseMoments,
    estimate_noise_prepared,
    moments_prepared,
    noise_ratios,
    start_states,
)
from ceemx.inference.ekf import ekf_prepared
from ceemx.infra.options import check_bool, check_real
from ceemx.infra.progress import task
from ceemx.lib.results import messages
from ceemx.lib.tree import as_jax
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = [
    "WHITE_LEVEL",
    "PredictionErrorCheck",
    "ResidualDiagnostics",
    "fit_diagnostics",
    "prediction_error_check",
    "residual_diagnostics",
]

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
        white: (m,) the whiteness test's verdict; ``independent`` (m, p) the input test's;
            ``unbiased`` (m,) the bias test's; ``nis_ok`` (m,) whether the NIS is inside its
            band. Each is an object array of ``True`` (passed), ``False`` (failed) or ``None``
            (not tested: the input and bias tests need white errors, so they are ``None`` where
            ``white`` is ``False``; every test needs two present samples; the input test a
            varying input). ``ratio_ok`` per field: the noise is consistent — (estimated /
            assumed std)² inside [1/F, F] when estimated, else the E-step ratio.
        largest: (m,) the largest |ẽ| per output (NaN where none is present); ``largest_at``
            its (record, step), 0-based; ``largest_p`` its Bonferroni p-value (the outlier test).
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
    largest: np.ndarray
    largest_at: tuple
    largest_p: np.ndarray
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

    @property
    def noise_verdict(self) -> str:
        """One verdict on the assumed noise: the end-of-fit check and the per-component ratios.

        ``"consistent"`` when both agree it is; otherwise ``"INCONSISTENT"`` naming the
        components outside their band (and saying when the overall ρ alone lies inside its
        band: the check pools every component, so it can hide one that is off).
        """
        off = [
            f"{name} {_COMPONENT[name]} {i + 1}"
            for name in NOISE_FIELDS
            for i in np.flatnonzero(~np.asarray(self.ratio_ok[name], dtype=bool))
        ]
        check = self.noise_check
        if check is not None and check.interpolating:
            return check.verdict
        if not off:
            if check is None or check.consistent:
                return "consistent"
            return "INCONSISTENT overall (rho outside its band; each component inside its band)"
        text = "INCONSISTENT: " + ", ".join(off)
        if check is not None and check.consistent:
            text += " (the overall rho, pooling every component, lies inside its band)"
        return text

    def summary(self) -> str:
        """Plain text: a few lines per component, then the problems found."""
        F = self.factor
        lines = ["Residual diagnostics"]
        if self.noise_check is not None:
            lines += self.noise_check.summary(verdict=self.noise_verdict).splitlines()
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
            tests = self._verdicts(i)
            lines.append(
                f"  output {i + 1}: NIS {self.nis[i]:.3g}, mean {self.bias[i]:+.3g}, "
                f"largest {self.largest[i]:.3g} ({_p_text(self.largest_p[i])}), "
                f"Box-Pierce {self.box_pierce[i]:.3g} (p = {self.box_pierce_p[i]:.2g}); "
                + ", ".join(tests)
            )
        if self.problems:
            lines.append("problems:")
            lines += [f"  - {p}" for p in self.problems]
        else:
            lines.append("no problem found")
        return "\n".join(lines)

    def _verdicts(self, i: int) -> list[str]:
        """Output i's prediction-error verdicts in words (``None``: not tested, said so)."""
        if self.white[i] is None:
            return ["not tested (fewer than two present samples)"]
        if not self.white[i]:
            return ["NOT white (input and bias tests not run: they need white errors)"]
        inputs = [v for v in self.independent[i] if v is not None]
        words = ["white"]
        if inputs:
            words.append("independent of inputs" if all(inputs) else "input-correlated")
        elif len(self.independent[i]):
            words.append("input test not run (constant inputs)")
        words.append("unbiased" if self.unbiased[i] else "biased")
        return words

    def __str__(self) -> str:
        """The report (:meth:`summary`): ``print(result.diagnostics())`` shows it."""
        return self.summary()

    def __repr__(self) -> str:
        return (
            f"ResidualDiagnostics(outputs={len(self.nis)}, lags={self.lags}, "
            f"problems={len(self.problems)})"
        )


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
            prior = GaussianPrior(indexed(as_jax(x1), b), system.process_noise)
        sol = ekf_prepared(system, data[b : b + 1], promote_tree(prior, system))
        e.append(np.asarray(data.y)[b] - np.asarray(sol.predicted_obs)[0])
        L = np.asarray(sol.innovation_chol)[0]
        s.append(np.sqrt(np.sum(L**2, axis=-1)))
    z = np.stack(e) / np.stack(s)
    return np.where(np.asarray(data.mask, bool), z, np.nan)


class Extremes(NamedTuple):
    """Per output, the largest standardised one-step error and the outlier test's p-value."""

    size: np.ndarray  # (m,) max |ẽ| over the present samples (NaN: none present)
    at: tuple  # per output, (record, step) of that error, 0-based (None: none present)
    p: np.ndarray  # (m,) min(1, N·P(|Z| ≥ size)): the chance of one that large among N


def _extremes(z: np.ndarray) -> Extremes:
    """:class:`Extremes` of (B, T, m) standardised errors, NaN where missing.

    Infinite errors (a filter that diverged) are left out: they are no sample of the noise.
    """
    m = z.shape[-1]
    size, p, at = np.full(m, np.nan), np.full(m, np.nan), []
    for i in range(m):
        a = np.abs(z[..., i])
        a = np.where(np.isfinite(a), a, np.nan)
        n = int(np.isfinite(a).sum())
        if n == 0:
            at.append(None)
            continue
        b, t = np.unravel_index(int(np.nanargmax(a)), a.shape)
        size[i] = a[b, t]
        p[i] = min(1.0, n * math.erfc(size[i] / math.sqrt(2.0)))
        at.append((int(b), int(t)))
    return Extremes(size, tuple(at), p)


def _error_statistics(inputs: Prepared, x1: np.ndarray, prior, M: int):
    """``(Correlations, NIS, Extremes)`` of the EKF's standardised one-step errors (lags 1…M)."""
    data = inputs.data
    z = _innovations(inputs.system, data, x1, prior)
    inside = np.arange(data.num_steps)[None, :] < _record_lengths(data)[:, None]
    return (*correlation_statistics(z, np.asarray(data.u), M, inside), _extremes(z))


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
    _check_request(system, lags, factor)
    check_bool("estimate", estimate)
    M = int(min(lags, data.num_steps - 1))
    system = _strong(system)
    inputs = prepare(system, data, states, identify=True)
    records = f"{data.batch_size} record{'s' if data.batch_size > 1 else ''}"
    with task(f"diagnostics: {records} of {data.num_steps} steps"):  # a line when it runs long
        noise = _noise_reading(system, inputs, estimate)
        ratio_ok, ratio_problems = _noise_verdicts(noise, factor)
        x1 = np.asarray(noise.states[:, 0])
        if states is not None:  # where the MAP failed, the given start
            x1 = np.where(np.isfinite(x1), x1, np.asarray(states)[:, 0])
        prior = system.initial_prior if initial is None else initial
        c, nis, extremes = _error_statistics(inputs, x1, prior, M)
        tests = _prediction_error_tests(c, nis, extremes)
    return ResidualDiagnostics(
        noise_ratios=noise.ratios,
        assumed_std=noise.assumed,
        estimated_std=noise.estimated,
        nis=nis,
        bias=c.mean,
        autocorrelation=c.autocorrelation,
        cross_correlation=c.cross_correlation,
        counts=c.counts,
        pair_counts=c.pair_counts,
        box_pierce=tests.box_pierce,
        box_pierce_p=tests.box_pierce_p,
        white=tests.white,
        independent=tests.independent,
        unbiased=tests.unbiased,
        nis_ok=tests.nis_ok,
        ratio_ok=ratio_ok,
        largest=extremes.size,
        largest_at=extremes.at,
        largest_p=extremes.p,
        lags=M,
        factor=factor,
        noise_check=noise_check,
        problems=tuple(noise.problems + ratio_problems + tests.problems),
    )


def _check_request(system: AbstractSystem, lags, factor) -> None:
    """Gaussian noise models, an integer ``lags`` ≥ 1 and a finite ``factor`` > 1, or raise."""
    for name in NOISE_FIELDS:
        if not getattr(system, name).is_gaussian:
            raise TypeError(
                f"residual diagnostics need Gaussian noise; system.{name} is "
                f"{type(getattr(system, name)).__name__}."
            )
    if isinstance(lags, bool) or not isinstance(lags, int | np.integer) or lags < 1:
        raise ValueError(f"`lags` must be an integer ≥ 1; got {lags!r}.")
    check_real("factor", factor)
    if not (np.isfinite(factor) and factor > 1):
        raise ValueError(f"`factor` must be finite and > 1; got {factor!r}.")


class _NoiseReading(NamedTuple):
    """The noise part of the diagnostics: per field, per component (module notes, item 1)."""

    ratios: dict  # one E-step's realised / assumed variance
    assumed: dict  # the assumed standard deviations
    estimated: dict | None  # the standard deviations the data say (None: not estimated)
    states: Any  # (B, T, n) the MAP states (NaN where the Laplace posterior is not finite)
    problems: list[str]


def _noise_reading(system: AbstractSystem, inputs, estimate: bool) -> _NoiseReading:
    """The Laplace E-step's noise ratios and, with ``estimate``, the noise the data say.

    Records of different lengths (padded to one T, the padding masked) are read up to their
    last observed sample: the states after it follow the dynamics alone, carry no information
    about the noise and would add the assumed process noise to the realised one (or overflow:
    the posterior spread of an unobserved unstable state grows without bound). Each length is
    one batch; their residual moments add up, and the noise estimate is each batch's pooled
    (variances weighted by their residual counts).
    """
    data, B = inputs.data, inputs.data.batch_size
    lengths = _record_lengths(data)
    parts = []
    for L in np.unique(lengths):
        idx = np.flatnonzero(lengths == L)
        parts.append((idx, _length_reading(system, inputs, int(L), idx, estimate)))
    states = np.full((B, data.num_steps, system.state_dim), np.nan)
    ok, log_ev = np.zeros(B, bool), np.full(B, np.nan)
    for idx, (nm, _) in parts:
        part_states = np.asarray(nm.states)
        states[idx, : part_states.shape[1]] = part_states
        ok[idx], log_ev[idx] = np.asarray(nm.ok), np.asarray(nm.log_evidence)
    moments = {
        key: as_jax(np.sum([np.asarray(nm.moments[key]) for _, (nm, _) in parts], axis=0))
        for key in parts[0][1][0].moments
    }
    nm = NoiseMoments(moments, as_jax(states), as_jax(log_ev), as_jax(ok))
    assumed = {name: _std(getattr(system, name)) for name in NOISE_FIELDS}
    estimated = None
    if ok.any():
        ratios = noise_ratios(system, nm)
        if estimate:
            estimated = _pooled_estimate([part for _, part in parts])
    else:
        ratios = {name: np.full(len(assumed[name]), np.nan) for name in NOISE_FIELDS}
    problems = []
    if not ok.all():
        problems.append(
            f"the Laplace posterior is not finite for trajectories {np.flatnonzero(~ok).tolist()}"
            " (a state neither observed nor pinned by a prior on x₁ makes the Gauss–Newton "
            "matrix singular): they are left out of the noise ratios."
        )
    return _NoiseReading(ratios, assumed, estimated, states, problems)


def _record_lengths(data: Trajectories) -> np.ndarray:
    """(B,) the steps of each record up to its last observed sample (at least 2; T if none)."""
    seen = np.asarray(np.asarray(data.mask).any(axis=-1))
    T = seen.shape[1]
    end = T - np.argmax(seen[:, ::-1], axis=1)
    return np.where(seen.any(axis=1), np.maximum(end, 2), T)


def _length_reading(system: AbstractSystem, inputs, L: int, idx: np.ndarray, estimate: bool):
    """(moments, estimated system or None) of the records ``idx``, read up to step ``L``."""
    data, states = inputs.data, inputs.states
    if L < data.num_steps or idx.size < data.batch_size:
        data = data[idx].head(L) if L < data.num_steps else data[idx]
        states = None if states is None else indexed(as_jax(states), (idx, slice(None, L)))
    part = Prepared(inputs.system, data, states)
    nm = moments_prepared(part.system, part.data, start_states(part))
    fitted = None
    if estimate and np.asarray(nm.ok).any():
        fitted, _, _ = estimate_noise_prepared(system, part.data, nm.states)
    return nm, fitted


def _pooled_estimate(parts: list) -> dict | None:
    """Per field, the estimated standard deviations of each batch, their variances pooled."""
    parts = [(nm, fitted) for nm, fitted in parts if fitted is not None]
    if not parts:
        return None
    out = {}
    for name in NOISE_FIELDS:
        total, weight = 0.0, 0.0
        for nm, fitted in parts:
            if name == "process_noise":
                w = float(nm.moments["dyn_count"])
            elif getattr(fitted, name).full_covariance:
                w = float(nm.moments["obs_full_count"])
            else:
                w = np.asarray(nm.moments["obs_count"], np.float64)
            total = total + w * _std(getattr(fitted, name)) ** 2
            weight = weight + w
        out[name] = np.sqrt(total / np.maximum(weight, 1e-300))
    return out


def _noise_verdicts(noise: _NoiseReading, factor: float) -> tuple[dict, list[str]]:
    """Per field, which components are consistent, and a message for each that is not.

    The verdict is the evidence maximiser's when estimated (unbiased either way), else the
    E-step's: the ratio must lie in [1/F, F].
    """
    ratio_ok, problems = {}, []
    ratios, assumed, estimated = noise.ratios, noise.assumed, noise.estimated
    for name in NOISE_FIELDS:
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
    return ratio_ok, problems


@dataclass
class _ErrorTests:
    """The one-step prediction-error tests per output (module notes, item 2).

    Verdicts are object arrays of ``True``/``False``, ``None`` until a test has run.
    """

    nis_ok: np.ndarray
    white: np.ndarray
    unbiased: np.ndarray
    independent: np.ndarray
    box_pierce: np.ndarray
    box_pierce_p: np.ndarray
    problems: list[str]

    @classmethod
    def untested(cls, m: int, p: int) -> _ErrorTests:
        """No test run yet: every verdict ``None``, no Box–Pierce statistic; m outputs, p inputs."""
        none = lambda *shape: np.full(shape, None, dtype=object)  # noqa: E731
        nan = np.full(m, np.nan)
        return cls(none(m), none(m), none(m), none(m, p), nan, nan.copy(), [])


def _prediction_error_tests(c: Correlations, nis: np.ndarray, extremes: Extremes) -> _ErrorTests:
    """NIS, outliers, whiteness, then bias and inputs (white errors only)."""
    M = c.lags
    tests = _ErrorTests.untested(len(nis), c.cross_correlation.shape[1])
    z_bonf = NormalDist().inv_cdf(1.0 - 0.005 / (2 * M + 1))
    z_bias = NormalDist().inv_cdf(1.0 - 0.0005)
    for i in range(len(nis)):
        N = c.counts[i]
        if N < 2:
            tests.problems.append(
                f"output {i + 1}: {int(N)} present prediction error(s): no test could be run."
            )
            continue
        message = _nis_test(i, nis[i], N)
        tests.nis_ok[i] = message is None
        if message:
            tests.problems.append(message)
        if extremes.p[i] < WHITE_LEVEL:
            tests.problems.append(_outlier_message(i, extremes))
        tests.box_pierce[i], tests.box_pierce_p[i] = _box_pierce(c, i)
        tests.white[i] = not tests.box_pierce_p[i] < WHITE_LEVEL
        if not tests.white[i]:
            tests.problems.append(_correlated_message(i, c, tests.box_pierce_p[i]))
            continue  # the bias and input tests assume white errors (their bands do): not run
        tests.unbiased[i] = not abs(c.mean[i]) * np.sqrt(N) > z_bias
        if not tests.unbiased[i]:
            tests.problems.append(
                f"output {i + 1}: the one-step prediction errors have mean {c.mean[i]:+.3g} "
                "(in predicted standard deviations): the model misses an offset."
            )
        for j in range(c.cross_correlation.shape[1]):
            verdict, message = _input_test(i, j, c, z_bonf)
            tests.independent[i, j] = verdict
            if message:
                tests.problems.append(message)
    return tests


def _outlier_where(i: int, extremes: Extremes) -> str:
    """Output i's largest error in words: ``record 2, step 58, 30 predicted SDs (p = …)``."""
    b, t = extremes.at[i]
    return (
        f"record {b + 1}, step {t + 1}, {extremes.size[i]:.3g} predicted SDs "
        f"({_p_text(extremes.p[i])} for the largest of this many Gaussian errors)"
    )


def _outlier_message(i: int, extremes: Extremes) -> str:
    """Output i's largest error is an outlier: where, how large, what to do."""
    return (
        f"output {i + 1}: an outlier among the one-step prediction errors at "
        f"{_outlier_where(i, extremes)}: a glitch in the data, or noise with heavier tails than "
        "the model's. A learned noise absorbs such a sample and the estimate follows it; mask it "
        "(Trajectories(mask=...)) and fit again."
    )


def _p_text(p: float) -> str:
    """``p = 0.0031``; ``p < 1e-300`` where it underflows to 0."""
    return "p < 1e-300" if p == 0 else f"p = {p:.2g}"


def _box_pierce(c: Correlations, i: int) -> tuple[float, float]:
    """Output i's Box–Pierce statistic Σ_k N_k r(k)², k = 1…M, and its χ²_M p-value."""
    q = float(np.sum(c.pair_counts[i, 1:] * c.autocorrelation[i, 1:] ** 2))
    return q, _chi2_sf(q, c.lags)


def _nis_test(i: int, nis: float, N: float) -> str | None:
    """The message when output i's NIS is outside the band of the end-of-fit ρ (else None)."""
    lo, hi = chi2_band(N)
    nis_lo, nis_hi = min(LOWER, lo), max(FACTOR, hi)
    if nis_lo <= nis <= nis_hi:
        return None
    way = "too tight (or the model misses dynamics)" if nis > 1 else "too loose"
    return (
        f"output {i + 1}: the one-step prediction errors are {nis:.3g}× their predicted variance "
        f"(NIS; {np.sqrt(nis):.3g}× in std): the assumed noise is {way}."
    )


def _correlated_message(i: int, c: Correlations, p_value: float) -> str:
    """Output i's errors are not white: at which lags they leave the pointwise band."""
    M = c.lags
    band = BAND_Z / np.sqrt(np.maximum(c.pair_counts[i, 1:], 1))
    out = [k for k in range(1, M + 1) if abs(c.autocorrelation[i, k]) > band[k - 1]]
    where = f"at lags {lag_ranges(out)}" if out else "over lags 1–" + str(M)
    return (
        f"output {i + 1}: the one-step prediction errors are correlated {where} (Box–Pierce "
        f"p = {p_value:.2g}): the model misses dynamics, or the noise ratio is off (a too tight "
        "process noise makes the filter sluggish)."
    )


def _input_test(i: int, j: int, c: Correlations, z_bonf: float) -> tuple[bool | None, str | None]:
    """(verdict, message): output i's errors against input j and the Bonferroni bound.

    ``(None, None)`` when not testable (a constant input), ``(True, None)`` when they do not
    correlate, ``(False, message)`` when they do.
    """
    M = c.lags
    row, xpairs = c.cross_correlation[i, j], c.cross_pair_counts[i, j]
    if not np.isfinite(row).any():
        return None, None
    scaled = np.abs(row) * np.sqrt(np.maximum(xpairs, 1))
    if not np.nanmax(scaled) > z_bonf:
        return True, None
    ks = np.arange(-M, M + 1)
    band = BAND_Z / np.sqrt(np.maximum(xpairs, 1))
    out = ks[np.abs(row) > band]
    pos = [int(k) for k in out if k >= 0]
    neg = [int(k) for k in out if k < 0]
    text = f"output {i + 1}: the one-step prediction errors correlate with input {j + 1}"
    if pos:
        text += (
            f" at lags {lag_ranges(pos)} (input before error): the model misses how the input "
            "acts (input dynamics, delay or feedthrough)"
        )
    if neg:
        text += f"{';' if pos else ''} at lags {lag_ranges(neg)} (error before input): feedback"
        text += " in the data"
    return False, text + "."


def _std(noise) -> np.ndarray:
    return np.sqrt(np.diagonal(np.asarray(noise.covariance(), np.float64)))


#: the level of the whiteness test (Box–Pierce), in the diagnostics and the summary alike
WHITE_LEVEL = 0.01


@dataclass(frozen=True)
class PredictionErrorCheck:
    """The whiteness test of the one-step prediction errors alone (module notes, item 2).

    What :func:`fit_summary <ceemx.identification.analysis.summary.fit_summary>` prints as its
    "one-step errors" row: the EKF innovations at the fit's end point, standardised per output,
    and each output's Box–Pierce test over lags 1…``lags`` at the diagnostics' level (1 %) —
    without the noise ratios and the noise estimate of :meth:`ceemx.FitResult.diagnostics`.
    White errors are what the intervals assume: the model holds at the estimate. Errors that are
    not white mean the model misses dynamics, θ sits at a local optimum (Lorenz from a start
    30 % off: σ = 1.98 against 10, Box–Pierce p = 1e-70, every interval excluding the truth), the
    noise ratio is off, or the EKF's linearisation is poor along this record.

    The row also names an outlier: an output whose largest error is improbable for Gaussian
    errors (:func:`residual_diagnostics`' outlier test) — one glitch that a learned noise absorbed.

    Attributes:
        p_values: (m,) each output's Box–Pierce p-value (NaN where under two errors are present).
        lags: M, the largest lag tested.
        extremes: the largest error per output, where, and the outlier test's p-value.
    """

    p_values: tuple[float, ...]
    lags: int
    extremes: Extremes | None = None

    @property
    def white(self) -> bool:
        """Whether no output's test rejects whiteness at 1 %."""
        return not any(p < WHITE_LEVEL for p in self.p_values)

    @property
    def outliers(self) -> tuple[int, ...]:
        """The outputs (0-based) whose largest error fails the outlier test at 1 %."""
        if self.extremes is None:
            return ()
        return tuple(i for i, p in enumerate(self.extremes.p) if p < WHITE_LEVEL)

    def __str__(self) -> str:
        text = self._whiteness()
        for i in self.outliers:
            assert self.extremes is not None
            text += (
                f"; an OUTLIER at output {i + 1}: {_outlier_where(i, self.extremes)}: a glitch "
                "in the data or heavier-tailed noise than the model's (a learned noise absorbs a "
                "glitch); mask it and fit again"
            )
        return text

    def _whiteness(self) -> str:
        ps = ", ".join(f"{p:.2g}" for p in self.p_values)
        head = f"Box–Pierce over lags 1–{self.lags} of the EKF's errors, p = {ps}"
        if not any(np.isfinite(self.p_values)):
            return (
                "not tested: under two finite prediction errors per output (the filter "
                "diverged or nothing is observed; FitResult.diagnostics())"
            )
        if self.white:
            return f"white ({head})"
        bad = [str(i + 1) for i, p in enumerate(self.p_values) if p < WHITE_LEVEL]
        return (
            f"NOT white at output {', '.join(bad)} ({head}): the model misses dynamics, θ is a "
            "local optimum, or the noise ratio is off; the intervals assume the model holds "
            "(FitResult.diagnostics())"
        )


def prediction_error_check(result: Any, lags: int = 25) -> PredictionErrorCheck | None:
    """:class:`PredictionErrorCheck` at a fit's end point; ``None`` where it cannot run.

    It cannot where a noise model is not Gaussian (the EKF needs it) or no trajectory has a
    usable end point. The EKF starts on each trajectory at the fit's x̂₁ with covariance Q (or
    the system's ``initial_prior``), as :func:`residual_diagnostics`.
    """
    system = result.system
    if result.problem is None or not all(getattr(system, f).is_gaussian for f in _COMPONENT):
        return None
    data, states = _fitted(result)
    if data is None:
        return None
    x1 = np.asarray(states)[:, 0]
    if not np.all(np.isfinite(x1)):
        return None
    M = int(min(lags, data.num_steps - 1))
    c, _, extremes = _error_statistics(prepare(_strong(system), data, None, identify=True), x1,
                                       system.initial_prior, M)  # fmt: skip
    ps = tuple(_box_pierce(c, i)[1] if n >= 2 else np.nan for i, n in enumerate(c.counts))
    return PredictionErrorCheck(ps, M, extremes)


def _fitted(result: Any):
    """``(data, states)`` of the trajectories a fit kept to its end; ``(None, None)``: none."""
    problem, _, states, weights = end_point(result)
    keep = np.flatnonzero(np.asarray(weights) > 0)
    if keep.size == 0:
        return None, None
    if keep.size == states.shape[0]:
        return problem.data, states
    return problem.data[keep], indexed(states, keep)


def fit_diagnostics(result: Any, **options) -> ResidualDiagnostics:
    """:meth:`ceemx.FitResult.diagnostics`: :func:`residual_diagnostics` at the fit's end point.

    The trajectories the fit left out (failed or excluded) are left out here too.

    Raises:
        ValueError: no trajectory took part in the fit to its end (every one failed).
    """
    data, states = _fitted(result)
    if data is None:
        raise ValueError(
            "no trajectory of this fit has a usable end point (every one failed or was "
            f"excluded; status: {'; '.join(sorted(set(messages(result.status))))}): there are no "
            "residuals to diagnose. residual_diagnostics(system, data) reads a model on data "
            "without a fit."
        )
    return residual_diagnostics(
        result.system, data, states, noise_check=result.noise_check, **options
    )
