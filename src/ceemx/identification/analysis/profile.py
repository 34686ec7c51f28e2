"""Profile-likelihood intervals of one parameter: :meth:`ceemx.FitResult.profile`.

The profile of a scalar parameter ψ (one entry of θ, named as the summary names it) is the
objective the fit maximised, maximised again over everything else with ψ held at each value:

* certainty-equivalent methods (:class:`ceemx.JointLM`, :class:`ceemx.Alternating`; solver flag
  ``uncertainty = "certainty-equivalent"``): J(x, θ) + log p(θ) (Eq. 9), maximised over the states
  and the other parameters;
* :class:`ceemx.LaplaceEM` (``uncertainty = "evidence"``): the Laplace log-evidence
  Σ_b log p(y_b | θ) + log p(θ), the states integrated out, maximised over the other parameters
  (learned noise scales included).

The level-``α`` interval is ``{ψ : 2·(max − profile(ψ)) ≤ χ²₁(α)}`` (3.841 at 95 %). Unlike the
Wald interval (a quadratic model of the objective at the estimate), it follows the objective
where the quadratic is poor: a skewed likelihood, a parameter near its bound. Each point is a
refit with ψ held (:mod:`~ceemx.identification.analysis.profile_points`: how, by which solver,
and the maximum the profile falls from); when the summary prints one:
:mod:`~ceemx.identification.analysis.profile_rule`.

The search (:func:`search`), on each side: from the Wald end ẑ ± q·σ_z of the unconstrained
coordinate z (q² = χ²₁(α); σ_z from :meth:`ceemx.FitResult.covariance`) step out, doubling the
step, until the profile has fallen by the threshold (at most ``max_steps`` points). A side with a
bound (:class:`ceemx.Positive`, ``lower``/``upper``) jumps, after two steps, to a point next to
the bound (10⁻⁶ of the way from it to the estimate): if the profile is still above the threshold
there the interval reaches the bound (``"bound"``: the end is the bound); a side without one
that has not crossed after the last step reports ``"limit"`` (the end is the last point searched,
so the interval is at least that wide). A crossing is then located by Brent's method on the
signed root √(2·drop) − q in natural units (nearly linear in ψ when the objective is nearly
quadratic), to ``xtol`` of the Wald half-width.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from statistics import NormalDist
from typing import Literal

import numpy as np
from scipy.optimize import root_scalar

from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.analysis.profile_points import ProfilePoints, RefitFailed
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import AbstractFitSolver

__all__ = ["Profile", "fit_profile", "search", "wald_covariance"]

End = Literal["found", "bound", "limit", "failed"]

#: a point next to a bound: this fraction of the way from the bound to the estimate
BOUND_GAP = 1e-6


@dataclasses.dataclass(frozen=True)
class Profile:
    """The profile-likelihood interval of one parameter (:meth:`ceemx.FitResult.profile`).

    Attributes:
        name: the parameter as the summary names it (``k``, ``A[0,1]``).
        estimate: the fit's estimate (natural units).
        lower, upper: the interval's ends (natural units).
        lower_end, upper_end: how each end was found — ``"found"`` (the profile crosses the
            threshold there), ``"bound"`` (it does not before the constraint's bound: the end is
            the bound), ``"limit"`` (not within the search: the end is the last point searched,
            the interval is at least that wide) or ``"failed"`` (a refit failed; NaN).
        wald: the Wald interval ``forward(ẑ ± q·σ_z)`` the summary prints beside it.
        level: the coverage (0.95).
        objective: ``"certainty-equivalent J"`` or ``"Laplace evidence"``.
        points: ``(value, 2·(max − profile))`` of every point computed, in increasing value
            (the estimate's drop is 0); NaN where a refit failed.
        evaluations: refits run (the polishing one included).
        seconds: wall time.
        notes: what the search met (a profile above the fit's end point, failed refits).
    """

    name: str
    estimate: float
    lower: float
    upper: float
    lower_end: End
    upper_end: End
    wald: tuple[float, float]
    level: float
    objective: str
    points: tuple[tuple[float, float], ...]
    evaluations: int
    seconds: float
    notes: tuple[str, ...] = ()

    @property
    def threshold(self) -> float:
        """χ²₁(level): the drop 2·(max − profile) at the interval's ends."""
        return NormalDist().inv_cdf(0.5 + self.level / 2.0) ** 2

    @property
    def interval(self) -> tuple[float, float]:
        """``(lower, upper)``."""
        return (self.lower, self.upper)

    def __str__(self) -> str:
        pct = f"{100 * self.level:g} %"
        words = {"found": "", "bound": " (the bound)", "limit": " (search limit)", "failed": ""}
        lines = [
            f"Profile of {self.name} ({self.objective}): estimate {self.estimate:.6g}",
            f"  {pct} profile interval  [{self.lower:.6g}{words[self.lower_end]}, "
            f"{self.upper:.6g}{words[self.upper_end]}]",
            f"  {pct} Wald interval     [{self.wald[0]:.6g}, {self.wald[1]:.6g}]",
            f"  {self.evaluations} refits, {self.seconds:.3g} s; threshold 2·(max − profile) = "
            f"{self.threshold:.4g}",
            "  value          2·(max − profile)",
            *(f"  {v:<14.6g} {d:.4g}" for v, d in self.points),
        ]
        return "\n".join([*lines, *(f"  note: {n}" for n in self.notes)])


def _side(points: ProfilePoints, side: int, max_steps: int, xtol: float) -> tuple[float, End]:
    """The interval's end on ``side`` (−1 lower, +1 upper) and how it was found."""
    bound = points.bounds[0 if side < 0 else 1]
    z_near = None
    if np.isfinite(bound):
        x_near = bound + BOUND_GAP * (points.estimate - bound)
        z_near = points.unconstrained(x_near)
    q2 = points.q**2
    z_in = points.z_hat
    for k in range(max_steps):
        z = points.z_hat + side * points.half_width * 2.0**k
        last = False
        if z_near is not None and (k >= 2 or side * (z - z_near) >= 0):
            z, last = z_near, True
        value = points.value_at(z)
        if not np.isfinite(value):
            return math.nan, "failed"
        if points.drop(value) >= q2:
            return _cross(points, z_in, z, xtol)
        if last:
            return float(bound), "bound"
        z_in = z
    return points.natural(z_in), "limit"


def _cross(points: ProfilePoints, z_in: float, z_out: float, xtol: float) -> tuple[float, End]:
    """Brent's method on √(2·drop) − q between a point inside and one outside."""
    a, b = points.natural(z_in), points.natural(z_out)

    def g(x: float) -> float:
        if x == a:
            z = z_in
        elif x == b:
            z = z_out
        else:
            z = points.unconstrained(x)
        d = points.drop(points.value_at(z))
        if not np.isfinite(d):
            raise RefitFailed("a refit failed inside the bracket")
        return math.sqrt(max(d, 0.0)) - points.q

    slope = float(points.problem.natural_jacobian(points.points[0].theta)[points.j])
    scale = abs(slope) * points.half_width  # the Wald half-width in natural units
    tol = xtol * (scale if np.isfinite(scale) and scale > 0 else abs(b - a))
    try:
        sol = root_scalar(g, bracket=(a, b), method="brentq", xtol=tol, rtol=1e-12, maxiter=40)
    except (RefitFailed, ValueError, RuntimeError):
        return math.nan, "failed"
    return (float(sol.root), "found") if sol.converged else (math.nan, "failed")


def search(points: ProfilePoints, max_steps: int, xtol: float, grid: int = 0) -> Profile:
    """The profile of ``points``: both ends, after the refit to the maximum where one is due.

    ``grid`` more points, evenly spaced in natural units over the interval and a quarter of
    its width beyond each end found (inside the bounds), for a figure.
    """
    if points.polish:
        points.polish_maximum()
        points.polish = ""
    lower, lower_end = _side(points, -1, max_steps, xtol)
    upper, upper_end = _side(points, +1, max_steps, xtol)
    if grid > 0 and np.isfinite(lower) and np.isfinite(upper):
        pad = 0.25 * (upper - lower)
        lo = lower - pad * (lower_end == "found")
        hi = upper + pad * (upper_end == "found")
        for x in np.linspace(lo, hi, grid + 2)[1:-1]:
            if points.bounds[0] < x < points.bounds[1]:
                points.value_at(points.unconstrained(float(x)))
    pts = sorted(
        (points.natural(p.z), points.drop(p.value) if np.isfinite(p.value) else math.nan)
        for p in points.points
    )
    failed = sum(1 for p in points.points if not np.isfinite(p.value))
    notes = list(points.notes)
    if failed:
        notes.append(f"{failed} refits failed (non-finite objective or a trajectory lost)")
    return Profile(
        points.name,
        points.estimate,
        lower,
        upper,
        lower_end,
        upper_end,
        points.wald(),
        points.level,
        points.objective_name,
        tuple((float(v), float(d)) for v, d in pts),
        points.evaluations,
        time.perf_counter() - points.t0,
        tuple(dict.fromkeys(notes)),
    )


def _index(problem: FitProblem, name: str) -> int:
    names = problem.parameter_names()
    key = name[1:] if name.startswith(".") and name[1:] in names else name
    if key not in names:
        raise KeyError(
            f"no trainable parameter named {name!r}; the fit's parameters are "
            f"{', '.join(names[:12])}{', …' if len(names) > 12 else ''}."
        )
    return names.index(key)


def wald_covariance(result, covariance) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(covariance, σ_z of every entry of θ, the covariance's warnings); computed if ``None``."""
    notes: list[str] = []
    if covariance is None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            covariance = result.covariance(hold_weak=True)
        notes = list(dict.fromkeys(str(w.message) for w in caught))
    c = np.asarray(covariance, np.float64)
    d = np.diagonal(c)
    return c, np.where(np.isfinite(d) & (d > 0), np.sqrt(np.abs(d)), np.nan), notes


def fit_profile(
    result,
    name: str,
    *,
    level: float = 0.95,
    max_epochs: int = 50,
    max_steps: int = 5,
    xtol: float = 1e-3,
    solver: AbstractFitSolver | None = None,
    grid: int = 0,
    covariance=None,
) -> Profile:
    """:meth:`ceemx.FitResult.profile`: the profile-likelihood interval of ``name``.

    Args:
        result: a :class:`ceemx.FitResult` of :func:`ceemx.fit`.
        name: one scalar parameter as the summary names it (``k``, ``process_noise.scale``,
            ``A[0,1]``).
        level: the interval's coverage, in (0, 1).
        max_epochs: epochs of each refit (warm-started next to its answer: a few suffice).
        max_steps: points stepped out on each side before a side is reported ``"limit"``.
        xtol: the crossing's tolerance, as a fraction of the bracket that holds it.
        solver: the refits' solver (default: :mod:`~ceemx.identification.analysis.profile_points`).
        grid: this many more points, evenly spaced over the interval and a quarter of its width
            beyond (for :func:`ceemx.evaluation.plots.plot_profile`; a refit each).
        covariance: θ's covariance, when already computed (default: ``result.covariance``).

    Returns:
        A :class:`Profile`.

    Raises:
        KeyError: for a name that is not a trainable parameter of the fit.
        ValueError: for a result without its problem, a ``level`` outside (0, 1), or an
            objective that is not finite at the fit's end point.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"`level` must be in (0, 1); got {level}.")
    problem, _, _, _ = end_point(result)
    j = _index(problem, name)
    _, sigma, notes = wald_covariance(result, covariance)
    points = ProfilePoints(result, j, float(sigma[j]), level, max_epochs, solver)
    points.notes += notes
    return search(points, max_steps, xtol, grid)
