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

from ceemx.identification.problem import FitProblem
from ceemx.lib.typing import States, Theta

__all__ = ["OUTLIER_OPTIONS", "Health", "trajectory_health"]

OUTLIER_OPTIONS = ("exclude", "warn", "keep")


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
    from ceemx.identification.problem import per_trajectory_nll, per_trajectory_offset

    data = problem.data
    nll = np.asarray(per_trajectory_nll(problem, theta, states), dtype=np.float64)
    system = problem.build(theta)
    c = np.asarray(per_trajectory_offset(problem, theta), dtype=np.float64)
    B, T, _ = data.y.shape
    n = system.state_dim
    count = (T - 1) * n + np.asarray(data.mask).reshape(B, -1).sum(axis=1)
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
