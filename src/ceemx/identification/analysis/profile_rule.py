"""When the summary prints a profile-likelihood interval: the rule of ``summary(intervals=...)``.

:meth:`ceemx.FitResult.summary` (``intervals="auto"``, the default) gives a parameter its profile
interval (:mod:`ceemx.identification.analysis.profile`) when

* its bound is near: the linear interval estimate ± 1.5·q·SE reaches it (no computation); or
* the objective is skewed: at a Wald end ẑ ± q·σ_z it has fallen by less than the quadratic
  model says — √(2·drop)/q < 0.9, the Wald interval is short on that side. The check
  (:func:`screen`) costs two evaluations of the objective and no refit: the other parameters
  move along the covariance's regression line θ̂ + Σ_{·j}/Σ_jj·(z − ẑ) (the quadratic model's
  conditional maximiser), the states are smoothed there (the warm start's compiled smoother) or
  the evidence evaluated (the E-step's). That value is exact for a quadratic objective and a
  lower bound of the profile otherwise, so a small fall is the profile's own, while a large one
  may be the path's: a Wald end beyond the profile's (√(2·drop)/q > 1) is not flagged, and such
  an interval errs on the safe side.

At most ``max_profiles`` (3) parameters are profiled (those near a bound first); the skewness is
checked on at most ``max_checks`` (6), the most uncertain relative to their values; nothing is
profiled for a fit that did not converge (no maximum to fall from). Each profile costs its
refits and, once per parameter, the compilation of the solver's programs for the problem with
that parameter held. ``intervals="profile"`` profiles every parameter, ``"wald"`` none.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from statistics import NormalDist
from typing import Any, Literal

import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.analysis.profile import Profile, search, wald_covariance
from ceemx.identification.analysis.profile_points import ProfilePoints
from ceemx.identification.problem import FitProblem
from ceemx.models.constraints import Unconstrained

__all__ = ["screen", "summary_intervals"]

#: the bound rule: the linear interval estimate ± NEAR_BOUND·q·SE reaches the bound
NEAR_BOUND = 1.5
#: the skewness rule: √(2·drop)/q at a Wald end below 1 − SKEW (the Wald interval is short there)
SKEW = 0.1


def screen(points: ProfilePoints, covariance: np.ndarray) -> list[float]:
    """√(2·drop)/q at the two Wald ends along the covariance's regression line (no refit).

    θ moves as the quadratic model's conditional maximiser, θ̂ + Σ_{·j}/Σ_jj·(z − ẑ), the
    states are smoothed (or the evidence evaluated) there: exact where the objective is
    quadratic (ratio 1), a lower bound of the profile elsewhere — a ratio below 1 means a
    profile flatter than the quadratic, above 1 a steeper one or a curved path.
    """
    c = np.asarray(covariance, np.float64)
    beta = np.where(np.isfinite(c[:, points.j]), c[:, points.j], 0.0) / c[points.j, points.j]
    theta = np.asarray(points.points[0].theta, np.float64)
    states = points.points[0].states
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref, _ = points.objective(points.points[0].theta, states, smooth=True)
        out = []
        for side in (-1, 1):
            guess = jnp.asarray(theta + beta * side * points.half_width, points.dtype)
            value, _ = points.objective(guess, states, smooth=True)
            d = 2.0 * (ref - value)
            out.append(math.sqrt(d) / points.q if np.isfinite(d) and d >= 0 else math.nan)
    return out


def summary_intervals(
    result,
    covariance,
    *,
    level: float = 0.95,
    mode: Literal["auto", "profile"] = "auto",
    max_profiles: int = 3,
    max_checks: int = 6,
) -> tuple[dict[int, Profile], list[str]]:
    """The profiles the summary prints: ``{entry of θ: Profile}`` and a note on what was done.

    ``mode="profile"``: every parameter with a Wald interval. ``"auto"``: the rule (module
    notes: a bound within 1.5 Wald half-widths; a Wald side too short), at most
    ``max_profiles`` parameters, the skewness checked on at most ``max_checks``; nothing for a
    fit that did not converge (its end point is not the maximum the profile falls from: each
    profile would first finish the fit — :meth:`ceemx.FitResult.profile` does).
    """
    if mode == "auto" and not result.converged:
        return {}, [
            "Intervals: Wald; no profile-likelihood interval, since the fit did not converge (a "
            "profile falls from the objective's maximum; FitResult.profile(name) refits to it "
            "first)."
        ]
    cov, sigma, _ = wald_covariance(result, covariance)
    has = [j for j in range(sigma.size) if np.isfinite(sigma[j])]
    points = _Points(result, sigma, level)
    if mode == "profile":
        reasons, checked = {j: "asked" for j in has}, (len(has), len(has))
    else:
        reasons, checked = _flagged(result, points, cov, has, level, max_profiles, max_checks)
    out: dict[int, Profile] = {}
    for j in reasons:
        try:
            out[j] = search(points(j), 5, 1e-3)
        except ValueError:
            continue
    if mode == "profile":
        text = ", ".join(f"{p.name} ({p.evaluations} refits)" for p in out.values())
        return out, [f"Intervals: profile likelihood: {text}."] if out else []
    return out, [_note(result, out, reasons, checked, max_profiles)]


class _Points(dict):
    """``j → ProfilePoints`` of a fit, made on first use (the screen's points are the search's)."""

    def __init__(self, result, sigma: np.ndarray, level: float):
        super().__init__()
        self.result, self.sigma, self.level = result, sigma, level

    def __call__(self, j: int) -> ProfilePoints:
        if j not in self:
            self[j] = ProfilePoints(self.result, j, float(self.sigma[j]), self.level, 50, None)
        return self[j]


def _flagged(result, points: _Points, cov, has, level, max_profiles, max_checks):
    """``({j: why}, (screened, to screen))``: the parameters the rule profiles, in order."""
    problem, theta, _, _ = end_point(result)
    nat = np.asarray(problem.natural(theta), np.float64)
    se = np.abs(np.asarray(problem.natural_jacobian(theta), np.float64)) * points.sigma
    reach = NEAR_BOUND * NormalDist().inv_cdf(0.5 + level / 2.0) * se
    bounds = _entry_bounds(problem)
    reasons = {
        j: "near its bound"
        for j in has
        if nat[j] - reach[j] <= bounds[j][0] or nat[j] + reach[j] >= bounds[j][1]
    }
    relative = se / np.maximum(np.abs(nat), 1e-300)
    rest = sorted((j for j in has if j not in reasons), key=lambda j: -relative[j])
    for j in rest[:max_checks]:
        try:
            ratios = screen(points(j), cov)
        except ValueError:
            continue
        if any(not np.isfinite(r) or r < 1.0 - SKEW for r in ratios):
            shown = " and ".join(f"{r:.3g}" for r in ratios)
            reasons[j] = f"skewed: √(2·drop)/q = {shown} at the Wald ends, not 1"
    order = sorted(reasons, key=lambda j: (reasons[j] != "near its bound", j))
    return {j: reasons[j] for j in order[:max_profiles]}, (min(len(rest), max_checks), len(rest))


def _note(result, out: dict[int, Profile], reasons, checked: tuple[int, int], most: int) -> str:
    """The message of ``intervals="auto"``: which intervals are profiles, and the rule."""
    names = result.problem.parameter_names()
    text = "Intervals: Wald (the quadratic model of the objective at the estimate)"
    if out:
        text += ", except the profile likelihood for " + ", ".join(
            f"{names[j]} ({reasons[j]})" for j in out
        )
    done, due = checked
    some = "all" if done >= due else f"{done} of {due}, the most uncertain"
    return text + (
        f". Profiled when a bound lies within {NEAR_BOUND:g} Wald half-widths or "
        f"√(2·drop)/q at a Wald end is below {1 - SKEW:g} (skewness checked on {some}), at most "
        f"{most} parameters; summary(intervals='profile') profiles every one, "
        "FitResult.profile(name) one."
    )


def _entry_bounds(problem: FitProblem) -> list[tuple[float, float]]:
    leaves = jtu.tree_leaves(problem.template)
    constraints: Sequence[Any] = problem.constraints or [Unconstrained()] * len(leaves)
    out: list[tuple[float, float]] = []
    for c, leaf in zip(constraints, leaves, strict=True):
        out += [c.bounds] * int(np.size(leaf))
    return out
