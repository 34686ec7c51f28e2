"""Per-trajectory health at the start of a fit: a robust outlier test on the fit's residuals.

One trajectory whose start states or observations are far outside what the model and its noise
allow (initial states of 10¹⁰, a record of pure noise, a wrong unit) dominates the shared θ of
every method: −J is a sum over trajectories, and the bad one's term can be orders of magnitude
larger than all the others together. :func:`fit <ceemx.fit>` therefore tests each trajectory
before the first epoch and, by default, fits without the ones flagged (``outliers="exclude"``);
``"warn"`` only names them, ``"keep"`` skips the test.

**The test.** For each trajectory b, the mean squared whitened residual at the start,

    r_b = 2·(−J_b − c_b) / N_b,

with c_b the noise models' −log p at zero residual (so −J_b − c_b is ½‖whitened residuals‖² for
Gaussian noise) and N_b the number of residual entries ((T − 1)·n dynamics, the observed
outputs, n for a prior). A correctly specified trajectory has r_b ≈ 1 at the truth; what matters
here is r_b against the others: with z_b = log r_b, med = median(z), s = 1.4826·median|z − med|
(the normalised median absolute deviation), b is flagged when

    z_b − med > max(k·s, log(ratio))    (k = 5, ratio = 100 by default),

i.e. its residuals are at least 100 times larger in mean square than the typical trajectory's
and an outlier among the batch's spread. A non-finite r_b is flagged too (the solvers also
exclude non-finite trajectories themselves). The test needs at least three trajectories (with
two, the median cannot tell which is the odd one); with fewer it flags only non-finite ones.
Heterogeneous batches (records of very different amplitude or quality) can trip it: pass
``outliers="keep"``, or give the noise model the scale of each record.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ceemx.identification.analysis.summary import describe_noise
from ceemx.identification.problem import FitProblem, per_trajectory_nll, per_trajectory_offset
from ceemx.inference.objective import whitened_residuals
from ceemx.infra.distributed import to_host
from ceemx.infra.policy import Runs, program
from ceemx.lib.typing import States, Theta

__all__ = [
    "ABSURD_MEAN_SQUARE",
    "OUTLIER_OPTIONS",
    "Health",
    "check_scale",
    "check_start",
    "failed_start",
    "near_bound",
    "no_finite_start",
    "trajectory_health",
]

OUTLIER_OPTIONS = ("exclude", "warn", "keep")

ABSURD_MEAN_SQUARE = 1e16
"""r_b above which a start is refused (residuals beyond 10⁸ noise standard deviations)."""

INVISIBLE_EFFECT = 1e-10
"""A parameter near its bound whose e-fold change moves the whitened residuals by less than this
fraction of their norm is refused at the start (:func:`check_scale`)."""

#: |d natural / dθ| at or below which a constrained entry counts as near its bound (softplus'
#: slope there is its distance to the bound) and is tested by :func:`check_scale`
_NEAR_BOUND_SLOPE = 1e-6


@dataclass(frozen=True)
class Health:
    """The start-of-fit test of every trajectory.

    Attributes:
        mean_square: (B,) r_b, the mean squared whitened residual at the start.
        flagged: (B,) whether b is an outlier (see the module notes).
        median: the median of the finite r_b.
        count: (B,) N_b, the residual entries of each trajectory.
    """

    mean_square: np.ndarray
    flagged: np.ndarray
    median: float
    count: np.ndarray

    def misfit(self, take: np.ndarray | None = None) -> float:
        """Σ_b ½·r_b·N_b over the trajectories ``take`` (all): −J − c, ½‖whitened residuals‖²."""
        r, n = self.mean_square, self.count
        take = np.ones(r.shape, bool) if take is None else np.asarray(take, bool)
        return float(np.sum(np.where(take, 0.5 * r * n, 0.0)))

    def describe(self, indices) -> str:
        """``b (r = …)`` for the given trajectories, e.g. for a warning."""
        return ", ".join(f"{int(b)} (r = {self.mean_square[b]:.3g})" for b in indices)


def trajectory_health(
    problem: FitProblem, theta: Theta, states: States, *, k: float = 5.0, ratio: float = 100.0
) -> Health:
    """The robust outlier test of the module notes, at (θ, x)."""
    data = problem.data
    nll = to_host(per_trajectory_nll(problem, theta, states)).astype(np.float64)
    system = problem.build(theta)
    c = to_host(per_trajectory_offset(problem, theta)).astype(np.float64)
    B, T, _ = data.y.shape
    n = system.state_dim
    count = (T - 1) * n + to_host(data.mask).reshape(B, -1).sum(axis=1)
    if system.initial_prior is not None:
        count = count + n
    with np.errstate(all="ignore"):
        r = 2.0 * (nll - c) / np.maximum(count, 1)
        finite = np.isfinite(r) & (r > 0)
        flagged = ~np.isfinite(r)
        median = float(np.median(r[finite])) if finite.any() else float("nan")
        if finite.sum() >= 3:
            z = np.log(np.where(finite, r, 1.0))
            med = float(np.median(z[finite]))
            mad = 1.4826 * float(np.median(np.abs(z[finite] - med)))
            flagged |= finite & (z - med > max(k * mad, np.log(ratio)))
    return Health(r, flagged, median, np.asarray(count, np.float64))


def no_finite_start(problem: FitProblem, theta: Theta, count: int) -> str:
    """The refusal of a start where J is not finite on any of ``count`` trajectories.

    It names the noise models (a scale near zero, or one whose square overflows, makes J
    infinite for any states) besides what else to check.
    """
    system = problem.build(theta)
    noise = "; ".join(
        f"{field}: {describe_noise(getattr(system, field))}"
        for field in ("process_noise", "obs_noise")
    )
    return (
        "no trajectory has a finite objective at the start: check the model's parameters and "
        f"noise ({noise}), the inputs and `x_init` (J is not finite for all {count} "
        "trajectories)."
    )


def check_start(
    problem: FitProblem,
    theta: Theta,
    states: States,
    health: Health | None = None,
    excluded: np.ndarray | None = None,
) -> Health:
    """Refuse a start no fit can be judged from: J not finite anywhere, or absurdly large.

    Every trajectory taking part (not ``excluded``) must have r_b ≤ :data:`ABSURD_MEAN_SQUARE`
    (1e16: whitened residuals of 10⁸ standard deviations). Beyond it J's rounding errors exceed
    any improvement a fit could make and the relative stopping rules compare against a
    meaningless scale: starts of 10¹⁰ on a Lorenz model stopped after two epochs as "converged"
    at J = −2.55e67. Such a start is a wrong unit or scale of ``x_init`` or of θ.

    Returns:
        The health record (``health`` as given, or computed).

    Raises:
        ValueError: naming the trajectories, their r_b and what to check (before any epoch).
    """
    health = trajectory_health(problem, theta, states) if health is None else health
    r = health.mean_square
    take = np.ones(r.shape, bool) if excluded is None else ~np.asarray(excluded, bool)
    if not np.any(np.isfinite(r) & take):
        raise ValueError(no_finite_start(problem, theta, int(take.sum())))
    with np.errstate(invalid="ignore"):
        absurd = take & np.isfinite(r) & (r > ABSURD_MEAN_SQUARE)
    if absurd.any():
        which = np.flatnonzero(absurd)
        shown = health.describe(which[:5]) + (", …" if which.size > 5 else "")
        several = which.size > 1
        raise ValueError(
            f"the start is too far from the data to fit: trajector{'ies' if several else 'y'} "
            f"{shown} ha{'ve' if several else 's'} a mean squared whitened residual r above "
            f"{ABSURD_MEAN_SQUARE:.0e} (residuals beyond 1e8 noise standard deviations). J's "
            "rounding errors then exceed any improvement a fit could make, so convergence "
            "cannot be judged. Check the scale and units of `x_init` and of the initial "
            "parameters and the noise models (or pass x_init=None for the solver's warm start)."
        )
    check_scale(problem, theta, states)
    return health


def check_scale(problem: FitProblem, theta: Theta, states: States) -> None:
    """Refuse a parameter started so near its bound that the data cannot show it.

    Tested: the entries near a bound (|dx/dθ| ≤ 1e-6, the transform saturated: a positive
    parameter below 1e-6), of models with Gaussian noise. For each, ‖∂r̃/∂θ_i‖, the change of the
    whitened residuals r̃ for an e-fold change of its distance to the bound, against ‖r̃‖. Below
    :data:`INVISIBLE_EFFECT` (1e-10) of it — ``y = c·√x`` with c = 1e-12 where y ≈ 1 — the
    parameter's whole effect on the model's outputs lies ten orders of magnitude below what the
    fit must explain: every step a solver takes in it is damped to nothing (its curvature is
    below any damping's floor, its gradient as small), it stays where it started and the fit
    stops "converged". The start is at an absurd scale against the data, as 1e-300 is against
    any. An entry the model does not use at all (an exactly zero derivative) is left to the
    identifiability report.

    Raises:
        ValueError: naming the parameter, its value, its effect and what to do (before any
            epoch).
    """
    near = near_bound(problem, theta)
    if not near.any():
        return
    system = problem.build(theta)
    if not (system.obs_noise.is_gaussian and system.process_noise.is_gaussian):
        return
    effect, size = (to_host(v) for v in _effects(problem, theta, states))
    size = float(size)
    invisible = near & (effect > 0) & (effect < INVISIBLE_EFFECT * size)
    if not invisible.any():
        return
    i = int(np.flatnonzero(invisible)[0])
    name = problem.parameter_names()[i]
    value = float(to_host(problem.natural(theta))[i])
    raise ValueError(
        f"`system.{name}` = {value:.6g} is too near its bound for the data to show it: an e-fold "
        f"change of it moves the fit's whitened residuals by {effect[i]:.3g} (in norm), "
        f"{effect[i] / size:.2g} of their size at the start ({size:.3g}), below "
        f"{INVISIBLE_EFFECT:.0e}. Its effect on the model's outputs is then far below anything "
        "the fit must explain: every step in it is damped to nothing, so it would stay at its "
        "start and the fit stop there. The start is at an absurd scale against the data (a "
        "unit error, or a placeholder value): start it at a value of the size the data "
        "suggest, or fix it (`ceemx.param(fixed=True)` or leave it out of `trainable`)."
    )


def near_bound(problem: FitProblem, theta: Theta) -> np.ndarray:
    """(P,) the entries of θ whose transform has saturated: |d natural / dθ| ≤ 1e-6.

    A positive parameter below 1e-6 (softplus' slope is its distance to the bound): its
    gradient in θ carries that slope, so no step of a solver moves it.
    """
    return np.abs(to_host(problem.natural_jacobian(theta))) <= _NEAR_BOUND_SLOPE


@program(runs=Runs.ONCE)  # only at a start with a parameter near its bound
def _effects(problem: FitProblem, theta: Theta, states: States):
    """(‖∂r̃/∂θ_i‖ for every entry i, ‖r̃‖): the whitened residuals' response and size."""

    def residuals(th):
        return whitened_residuals(problem.build(th), states, problem.data)

    def column(e):
        return jnp.sqrt(jnp.sum(jax.jvp(residuals, (theta,), (e,))[1] ** 2))

    size = jnp.sqrt(jnp.sum(residuals(theta) ** 2))
    return jax.lax.map(column, jnp.eye(theta.shape[0], dtype=theta.dtype)), size


@program(runs=Runs.ONCE)  # only after a start every trajectory failed at (a diagnosis)
def _start_gradient(problem: FitProblem, theta: Theta, states: States):
    def total(th, x):
        return jnp.sum(problem.per_trajectory(th, x)) + problem.neg_log_prior(th)

    return jax.grad(total, argnums=(0, 1))(theta, states)


def failed_start(problem: FitProblem, theta: Theta, states: States) -> str | None:
    """Why every trajectory failed at a start whose J is finite: the gradient, named; or ``None``.

    Called (and compiled) only when a solver's first evaluation failed on every trajectory: the
    gradient of −J (and the log-prior) at the start, and the entries where it is not finite —
    θ's by name and value, the states by trajectory, time step and component.
    """
    g_theta, g_x = (to_host(g) for g in _start_gradient(problem, theta, states))
    parts = []
    bad = ~np.isfinite(g_theta)
    if bad.any():
        names = problem.parameter_names()
        values = to_host(problem.natural(theta))
        shown = [f"{names[i]} = {values[i]:.6g}" for i in np.flatnonzero(bad)[:5]]
        more = ", …" if bad.sum() > 5 else ""
        parts.append(f"with respect to the parameters {', '.join(shown)}{more}")
    bad_x = ~np.isfinite(g_x)
    if bad_x.any():
        b, t, i = (int(k) for k in np.argwhere(bad_x)[0])
        which = np.flatnonzero(bad_x.reshape(bad_x.shape[0], -1).any(axis=1)).tolist()
        parts.append(
            f"with respect to the states of trajectories {which[:10]} (first: trajectory {b}, "
            f"time step {t}, component {i}, at x = {float(to_host(states)[b, t, i]):.6g})"
        )
    if not parts:
        return None
    return (
        "the fit cannot start: J is finite at the start but its gradient is not, "
        + "; ".join(parts)
        + ". Every method's first step needs it (the model is not differentiable there, e.g. a "
        "square root or logarithm at 0, or it overflows). Start elsewhere: other initial "
        "parameters, or `x_init` away from that point."
    )
