"""The end-of-fit noise check: are the fit's residuals consistent with the assumed noise?

A certainty-equivalent fit weighs dynamics against observations by the assumed noise scales, and
it converges whatever they are: with process noise 100× too tight the states cannot follow the
data and the model is bent to compensate, silently. After every fit, :func:`ceemx.fit` therefore
compares the realised whitened CE residuals at the end point with what the noise model allows
(``fit(..., diagnose=False)`` turns it off; :meth:`ceemx.FitResult.diagnostics` is the full
report, :mod:`ceemx.identification.analysis.diagnostics`).

**The statistic.** With r̂ the whitened residuals at the fit's (x̂, θ̂) — process residuals
L_Q⁻¹(x̂_{t+1} − f(x̂_t)), observation residuals L_R⁻¹(y_t − g(x̂_t)) (present samples only), and
L_P⁻¹(x̂₁ − μ) when the system has an ``initial_prior`` — over the trajectories taking part,

    ρ = Σ r̂² / d,   d = N_res − B·T·n − P,

with N_res the number of residual equations, B·T·n the states and P the trainable parameters fitted
to the same residuals. For a linear-Gaussian model at the MAP with the right noise, Σ r̂² is exactly
χ²(N_res − B·T·n) (the stacked whitened residual at the true states is N(0, I) and the MAP removes
its projection on the B·T·n state directions), so E[ρ] = 1 and sd(ρ) = √(2/d); the −P is the same
correction, first order, for θ fitted too (gauge freedoms such as a similarity transform of (A, C)
make it slightly conservative). Per-component mean squares (:attr:`NoiseCheck.process`,
:attr:`NoiseCheck.observation`) are reported for information only: each is biased low by an
unknown share of the B·T·n absorbed directions, so consistency is judged by ρ alone.

**The band.** The check warns when ρ lies outside [1/2, 4] (:data:`LOWER`, :data:`FACTOR`),
widened to the 0.05 % and 99.95 % quantiles of χ²_d / d when d is small. The two sides differ
because their causes do:

- *Above*: sd(ρ) = √(2/d) is 0.07 at d = 400 and 0.01 at d = 20 000, so a statistical bound would
  flag every model that is not exactly right — model error inflates ρ as well as a too tight
  noise does (structured residuals a nonlinear model off by a little leaves). F = 4 in variance
  (2× in standard deviation) is where the noise weighting starts to matter — the smoother's
  bandwidth follows Q/R — and leaves room for moderate model error; a guessed scale off by a
  decade is far outside. The message names both causes.
- *Below*: model error cannot lower ρ, so only sampling and the nonlinear CE approximation widen
  it: ρ at the truth was 1.005 ± 0.007 (mean ± SE over 100 linear-Gaussian records, d = 394, sd
  0.072 = √(2/d)) and 0.976 on the stiff three-state model (d = 1990); 1/2 is ≥ 5 sd at d ≥ 200.
  It has to be tighter than 1/4: the states absorb a too loose noise, so ρ moves much less than
  the scale error — process noise 10× too loose (std) gave ρ = 0.40 on the stiff model.

**Interpolation.** ρ cannot see an observation noise that collapsed: as σ_v → 0 the states
interpolate the data, the observation residuals vanish, the process residuals carry everything
and ρ stays near 1 (0.94 on a hysteretic record with a learned σ_v of 1e-10). The observation
group's mean squared whitened residual tells: it falls with σ_v/s, s the one-step spread the
process noise allows at the outputs. Below :data:`INTERPOLATION` (residuals 100× smaller than
their assumed standard deviation) while ρ is in the band or above it — the other residuals
carry it — the check is not consistent: the observation noise is orders of magnitude below what
the data resolve against the process noise, a collapsed estimate or a process noise far too
loose for it. (With ρ below the band every residual is small: a noise too loose, as above.)

ρ is an aggregate: a wrong scale of one component shows up diluted, so a ρ inside the band does
not prove every scale right (:meth:`ceemx.FitResult.diagnostics` estimates each). For d < 1 or
non-Gaussian noise there is no check (``None``).

**Solvers.** For :class:`ceemx.ParticleEM` the states are the mean of the FFBSi draws (the MAP
for a linear-Gaussian model; ρ = 1.13 at the true noise after 10 epochs on the test problem of
``tests/test_noise_diagnostics.py``, 22 with the process noise 10× too tight). A noise model
:class:`ceemx.LaplaceEM` learns fits the residuals by construction: with both learned the check is
recorded (:attr:`NoiseCheck.learned`) but never warns; with one learned, that one absorbs a wrong
fixed one (process noise fixed 10× too tight, observation noise learned: EM raised the observation
std 7× and ρ came out 1.15), which ρ cannot see — :meth:`ceemx.FitResult.diagnostics` estimates
every scale.

**Cost.** One small compiled program (:func:`square_sums`: the residuals summed per component, one
pass over the data, compiled once per system structure and data shape and reused by every later
fit of that shape) and a few host-side sums; no smoothing, no Jacobians.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ceemx.data.trajectories import Trajectories
from ceemx.inference.objective import residuals
from ceemx.infra.policy import Runs, program
from ceemx.lib.typing import States
from ceemx.models.system import AbstractSystem

__all__ = [
    "FACTOR",
    "INTERPOLATION",
    "LOWER",
    "NoiseCheck",
    "NoiseCheckWarning",
    "chi2_band",
    "interpolates",
    "noise_check",
    "square_sums",
]


class NoiseCheckWarning(UserWarning):
    """The end-of-fit noise check's warning.

    Its own category, so that a script fitting many records at fixed, known-inconsistent noise
    (the paper's experiments) can collect or filter it:
    ``warnings.filterwarnings("ignore", category=ceemx.NoiseCheckWarning)``.
    """


#: the upper bound F of ρ (and of the per-component ratios, [1/F, F]): 2× in standard deviation
FACTOR = 4.0
#: the lower bound of ρ (model error cannot lower ρ, so it is tighter; module notes)
LOWER = 0.5

#: the observation residuals' mean squared whitened value below which the states interpolate
#: the data (residuals 100× below their assumed standard deviation; module notes)
INTERPOLATION = 1e-4

#: two-sided tail probability of the statistical widening of the band for small d.o.f.
_TAIL = 1e-3


def chi2_band(dof: float, tail: float = _TAIL) -> tuple[float, float]:
    """The (tail/2, 1 − tail/2) quantiles of χ²_d / d (Wilson–Hilferty; good to 1 % for d ≥ 3)."""
    z = NormalDist().inv_cdf(1.0 - tail / 2.0)
    s = np.sqrt(2.0 / (9.0 * dof))
    lo = max(1.0 - 2.0 / (9.0 * dof) - z * s, 0.0) ** 3
    hi = (1.0 - 2.0 / (9.0 * dof) + z * s) ** 3
    return float(lo), float(hi)


def _sums_single(system: AbstractSystem, x, y, u, mask):
    # Gaussian noise only (checked by noise_check before tracing): `whiten` exists.
    obs_noise: Any = system.obs_noise
    process_noise: Any = system.process_noise
    r_obs, r_dyn = residuals(system, x, y, u)
    obs = jnp.sum(jax.vmap(obs_noise.whiten)(r_obs, mask) ** 2, axis=0)
    dyn = jnp.sum(jax.vmap(process_noise.whiten)(r_dyn) ** 2, axis=0)
    prior = jnp.zeros_like(x[0])
    if system.initial_prior is not None:
        prior_noise: Any = system.initial_prior.noise
        prior = prior_noise.whiten(x[0] - system.initial_prior.mean) ** 2
    return obs, dyn, prior


@program(runs=Runs.ONCE)
def square_sums(
    system: AbstractSystem, states: States, data: Trajectories
) -> tuple[Float[Array, "B m"], Float[Array, "B n"], Float[Array, "B n"]]:
    """Per trajectory, the squared whitened residuals summed over time per component.

    Returns:
        ``(observation (B, m), process (B, n), prior (B, n))`` — zeros for the prior when the
        system has none. Masked observations contribute zero. Compiled once per system structure
        and data shape.
    """
    return jax.vmap(_sums_single, in_axes=(None, 0, 0, 0, 0))(
        system, states, data.y, data.u, data.mask
    )


@dataclass(frozen=True, eq=False)
class NoiseCheck:
    """The end-of-fit noise check (module notes).

    Attributes:
        ratio: ρ = Σ r̂² / d over the trajectories taking part (≈ 1 when consistent).
        dof: d = N_res − B·T·n − P.
        residuals: N_res, the number of residual equations.
        band: (lo, hi): no warning inside; [:data:`LOWER`, :data:`FACTOR`] widened to the
            χ²_d/d quantiles when d is small.
        process: (n,) realised mean squared whitened process residual per state (biased low;
            for information).
        observation: (m,) the same per output over its present samples (NaN if never observed).
        prior: (n,) the squared whitened x₁ prior residual per state, averaged over trajectories,
            or ``None`` without an ``initial_prior``.
        groups: ``{"process": (sum, count), "observation": (sum, count), "prior": ...}``: Σ r̂²
            and the number of residual equations of each group.
        per_trajectory: (B,) Σ r̂² of each trajectory (NaN for those not taking part).
        learned: the noise fields the solver learned (``"process_noise"``, ``"obs_noise"``); the
            check does not warn when every noise model was learned.
        converged: whether the fit converged (a fit stopped early leaves model error in ρ).
        message: the warning text (``None`` when consistent or not warned about).
        interpolating: the observation residuals' mean squared whitened value is below
            :data:`INTERPOLATION`: the states interpolate the data (module notes).
    """

    ratio: float
    dof: float
    residuals: int
    band: tuple[float, float]
    process: np.ndarray
    observation: np.ndarray
    prior: np.ndarray | None
    groups: dict
    per_trajectory: np.ndarray | None = None
    learned: tuple[str, ...] = ()
    converged: bool = True
    message: str | None = None
    interpolating: bool = False

    @property
    def consistent(self) -> bool:
        """Whether ρ lies inside :attr:`band` and the states do not interpolate the data."""
        return bool(self.band[0] <= self.ratio <= self.band[1]) and not self.interpolating

    @property
    def verdict(self) -> str:
        """``"consistent"``, ``"INCONSISTENT"`` or ``"DEGENERATE"`` (the states interpolate)."""
        if self.interpolating:
            return "DEGENERATE (the states interpolate the data)"
        return "consistent" if self.consistent else "INCONSISTENT"

    @property
    def std_ratio(self) -> float:
        """√ρ: the realised / assumed standard deviation."""
        return float(np.sqrt(self.ratio))

    def summary(self, verdict: str | None = None) -> str:
        """A few lines of plain text; ``verdict`` replaces :attr:`verdict` (the diagnostics')."""
        verdict = self.verdict if verdict is None else verdict
        lines = [
            f"noise check (CE residuals at the fit): rho = {self.ratio:.3g} "
            f"(sqrt = {self.std_ratio:.3g} in std; band [{self.band[0]:.3g}, {self.band[1]:.3g}], "
            f"d.o.f. {self.dof:.0f} of {self.residuals} residuals): {verdict}",
            "  mean squared whitened residual (biased low): process "
            + _components(self.process, "state")
            + "; observation "
            + _components(self.observation, "output"),
        ]
        if self.learned:
            lines.append(f"  learned by the solver: {', '.join(self.learned)}")
        if self.message:
            lines.append("  " + self.message)
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"NoiseCheck(ratio={self.ratio:.3g}, dof={self.dof:.0f}, consistent={self.consistent})"
        )


def _components(values: np.ndarray, name: str) -> str:
    return ", ".join(f"{name} {i + 1}: {v:.3g}" for i, v in enumerate(np.asarray(values)))


def noise_check(
    system: AbstractSystem,
    data: Trajectories,
    states: States,
    *,
    weights=None,
    n_params: int = 0,
    learned: Sequence[str] = (),
    converged: bool = True,
    band: tuple[float, float] = (LOWER, FACTOR),
) -> NoiseCheck | None:
    """The noise check of the module notes at (x̂, θ̂) = (``states``, ``system``).

    Args:
        system: the fitted model (its noise is the assumed noise).
        data: the B trajectories of the fit.
        states: (B, T, n) the fitted states.
        weights: (B,) trajectory weights; those ≤ 0 (failed) are left out (``None``: all).
        n_params: P, the number of parameters fitted to the same residuals.
        learned: the noise fields the solver learned.
        converged: whether the fit converged (changes the message only).
        band: the bounds of ρ (widened for small d.o.f.).

    Returns:
        A :class:`NoiseCheck` with :attr:`~NoiseCheck.message` set when ρ is outside the band
        (and some noise was not learned), or ``None`` when the noise is not Gaussian, no
        trajectory takes part, or there are no degrees of freedom (d < 1).
    """
    prior_noise = None if system.initial_prior is None else system.initial_prior.noise
    noises = (system.process_noise, system.obs_noise, prior_noise)
    if not all(noise is None or noise.is_gaussian for noise in noises):
        return None
    B, T, n = states.shape
    keep = np.ones(B, bool) if weights is None else np.asarray(weights) > 0
    obs, dyn, pri = (np.asarray(a, np.float64) for a in square_sums(system, states, data))
    per_trajectory = obs.sum(1) + dyn.sum(1) + pri.sum(1)
    finite = keep & np.isfinite(per_trajectory)
    if not finite.any():
        return None
    b = int(finite.sum())
    obs_count = np.asarray(data.mask, bool)[finite].sum(axis=(0, 1)).astype(np.float64)
    groups = {
        "process": (float(dyn[finite].sum()), b * (T - 1) * n),
        "observation": (float(obs[finite].sum()), int(obs_count.sum())),
    }
    prior = None
    if system.initial_prior is not None:
        groups["prior"] = (float(pri[finite].sum()), b * n)
        prior = pri[finite].mean(axis=0)
    count = sum(c for _, c in groups.values())
    dof = float(count - b * T * n - n_params)
    if dof < 1:
        return None
    ratio = float(per_trajectory[finite].sum()) / dof
    lo, hi = chi2_band(dof)
    with np.errstate(invalid="ignore", divide="ignore"):
        observation = np.where(obs_count > 0, obs[finite].sum(axis=0) / obs_count, np.nan)
    check = NoiseCheck(
        ratio=ratio,
        dof=dof,
        residuals=count,
        band=(min(band[0], lo), max(band[1], hi)),
        process=dyn[finite].sum(axis=0) / max(b * (T - 1), 1),
        observation=observation,
        prior=prior,
        groups=groups,
        per_trajectory=np.where(finite, per_trajectory, np.nan),
        learned=tuple(learned),
        converged=converged,
        interpolating=_interpolating(groups, ratio, min(band[0], lo)),
    )
    if check.consistent or {"process_noise", "obs_noise"} <= set(learned):
        return check
    return dataclasses.replace(check, message=_message(check))


def _interpolating(groups: dict, ratio: float, lower: float) -> bool:
    """The observation residuals vanish while the others carry ρ into the band or above it.

    With ρ below the band every residual is small: the noise is too loose, a case of its own.
    """
    return interpolates(*groups["observation"]) and ratio >= lower


def interpolates(total: float, count: float | int) -> bool:
    """Whether the states interpolate the data (module notes).

    ``total``: the observation residuals' squared whitened values summed over ``count`` of them;
    their mean below :data:`INTERPOLATION`.
    """
    return bool(count > 0 and total < INTERPOLATION * count)


def _interpolation_message(check: NoiseCheck) -> str:
    total, count = check.groups["observation"]
    return (
        f"the states interpolate the data: the observation residuals are {total / count:.3g}× "
        f"their assumed variance (below {INTERPOLATION:g}), so rho = {check.ratio:.3g} cannot "
        "judge the noise. The observation noise is orders of magnitude below the one-step "
        "spread the process noise allows at the outputs: a collapsed (learned) observation "
        "noise, or a process noise far too loose for it; a CE fit then fits θ to one-step "
        "residuals and may free-run badly."
    )


_TIGHT = {
    "observation": "the observation residuals carry it ({:.3g}× their assumed variance): the "
    "process noise may be too tight for the states to follow the data, or the observation noise "
    "too small",
    "process": "the process residuals carry it ({:.3g}× their assumed variance): the process "
    "noise is too small for how the states must move to fit the data",
    "prior": "the initial-state prior residual carries it ({:.3g}× its assumed variance): the "
    "prior on x₁ is too tight",
}
_LOOSE = {
    "observation": "the observation residuals are {:.3g}× their assumed variance: the states "
    "follow the data more closely than the observation noise allows (the observation noise may "
    "be too large, or the process noise too loose)",
    "process": "the process residuals are {:.3g}× their assumed variance: the process noise is "
    "larger than the states need",
    "prior": "the initial-state prior residual is {:.3g}× its assumed variance: the prior on x₁ "
    "is wider than it needs to be",
}


def _message(check: NoiseCheck) -> str:
    """The warning: which way, by how much, which residual group carries it, what to do."""
    if check.interpolating and check.band[0] <= check.ratio <= check.band[1]:
        return _interpolation_message(check) + _ADVICE
    rho = check.ratio
    # Each group's excess over its share of the expected Σ r̂² (the d.o.f. apportioned by size).
    share = check.dof / check.residuals
    excess = {g: s - c * share for g, (s, c) in check.groups.items() if c > 0}
    tight = rho > 1
    group = (max if tight else min)(excess, key=lambda g: excess[g])
    total, count = check.groups[group]
    way = "too tight, or the model misses dynamics" if tight else "too loose"
    text = (
        f"the assumed noise is {way}: the fit's whitened residuals are {np.sqrt(rho):.3g}× the "
        f"assumed standard deviation (rho = {rho:.3g} in variance, corrected for the "
        f"{check.residuals - check.dof:.0f} fitted states and parameters; consistent within "
        f"[{check.band[0]:.3g}, {check.band[1]:.3g}]); "
        + (_TIGHT if tight else _LOOSE)[group].format(total / count)
        + "."
    )
    per = check.per_trajectory
    if tight and per is not None and np.sum(np.isfinite(per)) >= 3:
        worst = int(np.nanargmax(per))
        part = per[worst] / np.nansum(per)
        if part > 0.5:  # one trajectory outweighs all the others together
            text = (
                f"trajectory {worst} alone carries {100 * part:.0f} % of the fit's squared "
                "whitened residuals: an outlier? (fit(..., outliers='exclude'), "
                "ceemx.identification.fitting.health). Otherwise " + text
            )
    if not check.converged:
        text += " The fit stopped before convergence: part of this may be model error."
    if check.learned:
        text += f" The solver learned {', '.join(check.learned)}; the rest was fixed."
    if check.interpolating:
        text += " " + _interpolation_message(check)
    return text + _ADVICE


_ADVICE = (
    " Learn the noise: fit(..., noise='learn'), ceemx.estimate_noise(system, data) (scales "
    "from the data at this θ) or solver=ceemx.LaplaceEM() with trainable noise; "
    "FitResult.diagnostics() gives the full report (ceemx.identification.analysis.noise_check)."
)
