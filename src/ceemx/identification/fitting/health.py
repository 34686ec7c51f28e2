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

import numpy as np

from ceemx.identification.problem import FitProblem, per_trajectory_nll, per_trajectory_offset
from ceemx.infra.distributed import to_host
from ceemx.lib.typing import States, Theta

__all__ = ["ABSURD_MEAN_SQUARE", "OUTLIER_OPTIONS", "Health", "check_start", "trajectory_health"]

OUTLIER_OPTIONS = ("exclude", "warn", "keep")

ABSURD_MEAN_SQUARE = 1e16
"""r_b above which a start is refused (residuals beyond 10⁸ noise standard deviations)."""


@dataclass(frozen=True)
class Health:
    """The start-of-fit test of every trajectory.

    Attributes:
        mean_square: (B,) r_b, the mean squared whitened residual at the start.
        flagged: (B,) whether b is an outlier (see the module notes).
        median: the median of the finite r_b.
    """

    mean_square: np.ndarray
    flagged: np.ndarray
    median: float

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
    return Health(r, flagged, median)


def check_start(
    problem: FitProblem,
    theta: Theta,
    states: States,
    health: Health | None = None,
    excluded: np.ndarray | None = None,
) -> None:
    """Refuse a start no fit can be judged from: J not finite anywhere, or absurdly large.

    Every trajectory taking part (not ``excluded``) must have r_b ≤ :data:`ABSURD_MEAN_SQUARE`
    (1e16: whitened residuals of 10⁸ standard deviations). Beyond it J's rounding errors exceed
    any improvement a fit could make and the relative stopping rules compare against a
    meaningless scale: starts of 10¹⁰ on a Lorenz model stopped after two epochs as "converged"
    at J = −2.55e67. Such a start is a wrong unit or scale of ``x_init`` or of θ.

    Raises:
        ValueError: naming the trajectories, their r_b and what to check (before any epoch).
    """
    health = trajectory_health(problem, theta, states) if health is None else health
    r = health.mean_square
    take = np.ones(r.shape, bool) if excluded is None else ~np.asarray(excluded, bool)
    if not np.any(np.isfinite(r) & take):
        raise ValueError(
            "no trajectory has a finite objective at the start: check the model's parameters "
            "and noise, the inputs and `x_init` (J is not finite for all "
            f"{int(take.sum())} trajectories)."
        )
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
