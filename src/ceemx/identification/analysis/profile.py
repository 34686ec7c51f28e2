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
where the quadratic is poor: a skewed likelihood, a parameter near its bound.

How each point is computed: the fit problem with ψ held fixed (a ``trainable`` filter without its
leaf; an entry of a larger array, which cannot leave θ on its own, stays in θ with no effect on
the objective: its constraint's transform reads it through ``stop_gradient``, so its gradient and
curvature are zero and no solver moves it — Marquardt's damping keeps such a direction still) is
refitted from the nearest point already computed — its θ and states — by the library's solver
interface (``init``/``step``/``terminate``/``postprocess``, at most ``max_epochs`` epochs, the
solver's tolerances): the fit's own solver for Laplace EM (without its coarse start), and
:class:`ceemx.JointLM` for the certainty-equivalent methods (the fit's own when it is one; J is the
same objective, and Algorithm 1 would take many epochs to settle each point). The objective is
then evaluated at the refit's end point exactly as at the fit's: J from the states, or the
log-evidence from a MAP smoothing and the log-determinant of its Gauss–Newton matrix (with the
smoother of the fit's solver, as
:func:`~ceemx.identification.analysis.uncertainty.evidence_covariance` does).
(The epochs run as :func:`ceemx.fit` runs them, without its per-call checks, warm start,
health test and end-of-fit check: the inputs were checked by the fit, and
:mod:`ceemx.identification.fitting` builds :class:`~ceemx.FitResult` on this module, so it
cannot be called from here.) The maximum is the objective at the fit's end point; after
Algorithm 1 (refits by another method) the larger of it and a refit with ψ held at its estimate;
after a fit that did not converge, the larger of it and a refit with nothing held (the fit
continued by the refits' solver). A point above the maximum raises it (a note says so when by
more than 0.01 in 2·Δ).

The search, on each side: from the Wald end ẑ ± q·σ_z of the unconstrained coordinate z (q² =
χ²₁(α); σ_z from :meth:`ceemx.FitResult.covariance`) step out, doubling the step, until the
profile has fallen by the threshold (at most ``max_steps`` points). A side with a bound
(:class:`ceemx.Positive`, ``lower``/``upper``) jumps, after two steps, to a point next to the
bound (10⁻⁶ of the way from it to the estimate): if the profile is still above the threshold
there the interval reaches the bound (``"bound"``: the end is the bound); a side without one that
has not crossed after the last step reports ``"limit"`` (the end is the last point searched, so
the interval is at least that wide). A crossing is then located by Brent's method on the signed
root √(2·drop) − q in natural units (nearly linear in ψ when the objective is nearly quadratic).

:func:`summary_intervals` is the rule :meth:`ceemx.FitResult.summary` applies by default
(``intervals="auto"``). A parameter gets its profile interval when

* its bound is near: the linear interval estimate ± 1.5·q·SE reaches it (no computation); or
* the objective is skewed: at a Wald end ẑ ± q·σ_z it has fallen by less than the quadratic
  model says — √(2·drop)/q < 0.9, the Wald interval is short on that side. The check costs two
  evaluations of the objective and no refit: the other parameters move along the covariance's
  regression line θ̂ + Σ_{·j}/Σ_jj·(z − ẑ) (the quadratic model's conditional maximiser), the
  states are smoothed there (the warm start's compiled smoother) or the evidence evaluated (the
  E-step's). That value is exact for a quadratic objective and a lower bound of the profile
  otherwise, so a small fall is the profile's own, while a large one may be the path's: a Wald
  end beyond the profile's (√(2·drop)/q > 1) is not flagged, and such an interval errs on the
  safe side.

At most ``max_profiles`` (3) parameters are profiled (those near a bound first); the skewness is
checked on at most ``max_checks`` (6), the most uncertain relative to their values. Each profile
costs its refits and, once per parameter, the compilation of the solver's programs for the
problem with that parameter held.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence
from statistics import NormalDist
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from scipy.optimize import root_scalar

from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import AbstractFitSolver, trajectory_log_likelihood
from ceemx.identification.solvers.joint import JointLM
from ceemx.inference.posterior import gaussian_posterior
from ceemx.inference.smoother import LMSmoother, smooth_prepared
from ceemx.infra.policy import Runs
from ceemx.lib.results import RESULTS
from ceemx.lib.tree import trace_numbers
from ceemx.models.constraints import AbstractConstraint, Unconstrained

__all__ = ["Profile", "fit_profile", "summary_intervals"]

End = Literal["found", "bound", "limit", "failed"]

#: the bound rule: the linear interval estimate ± NEAR_BOUND·q·SE reaches the bound
NEAR_BOUND = 1.5
#: the skewness rule: √(2·drop)/q at a Wald end below 1 − SKEW (the Wald interval is short there)
SKEW = 0.1
#: a point next to a bound: this fraction of the way from the bound to the estimate
BOUND_GAP = 1e-6
#: a rise of the objective above the fit's end point (in 2·Δ, the drop's units) worth a note
NOTED_RISE = 0.01


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


class _Failed(Exception):
    """A refit or an evaluation of the objective failed (non-finite, a trajectory lost)."""


@dataclasses.dataclass
class _Point:
    z: float
    value: float  # the objective (not the drop), NaN when failed
    theta: Any  # full θ (the problem's coordinates)
    states: Any


class _Profiler:
    """The profile of entry ``j`` of θ: points computed on demand, warm-started, kept."""

    def __init__(self, result, j: int, sigma_z: float, level: float, max_epochs: int, solver):
        """The profile of entry ``j`` of ``result``'s θ (σ_z: its Wald standard deviation)."""
        problem, theta, states, weights = end_point(result)
        self.problem, self.weights, self.j, self.dtype = problem, weights, j, theta.dtype
        self.name = problem.parameter_names()[j]
        self.level, self.q = level, NormalDist().inv_cdf(0.5 + level / 2.0)
        self.max_epochs = max_epochs
        self.evidence = result.solver.uncertainty == "evidence"
        self.objective = "Laplace evidence" if self.evidence else "certainty-equivalent J"
        self.solver, same = _refit_solver(result.solver, solver, theta.dtype)
        own = getattr(result.solver, "smoother", None)
        if self.evidence:  # the fit's E-step program
            own = LMSmoother(rtol=1e-14) if own is None else own
            self.smoother = trace_numbers(own, theta.dtype)
        else:  # the warm start's program (AbstractFitSolver.initial_states), tighter
            chunk = own.batch_chunk if isinstance(own, LMSmoother) else None
            self.smoother = LMSmoother(rtol=1e-12, batch_chunk=chunk)
        self.runs = Runs.EVERY_EPOCH if result.solver.smooths_each_epoch else Runs.ONCE
        self.leaf, self.offset, self.position, self.mask = _locate(problem, j)
        self.constraint = (problem.constraints or [Unconstrained()] * (self.leaf + 1))[self.leaf]
        self.z_hat = float(np.asarray(theta)[j])
        self.estimate = self.natural(self.z_hat)
        self.sigma_z = sigma_z
        self.notes: list[str] = []
        self.evaluations = 0
        self.t0 = time.perf_counter()
        self.ok_weights = np.asarray(weights) > 0
        value, states = self._objective(theta, states, smooth=False)
        self.points = [_Point(self.z_hat, value, theta, states)]
        self.maximum = value
        if not np.isfinite(value):
            raise ValueError(f"the objective is not finite at the fit's end point ({value}).")
        # the maximum: a converged fit of the refits' method is at it; one of another method
        # (Algorithm 1) is refitted with ψ held at its estimate (the refits' own program); one
        # that did not converge is refitted with nothing held
        self.polish = "" if not self._free() or (result.converged and same) else "held"
        if not result.converged and self._free():
            self.polish = "free"

    # ---- coordinates -------------------------------------------------------------------------

    def natural(self, z: float) -> float:
        return float(self.constraint.forward(jnp.asarray(z, self.dtype)))

    def unconstrained(self, x: float) -> float:
        return float(self.constraint.inverse(jnp.asarray(x, self.dtype)))

    @property
    def bounds(self) -> tuple[float, float]:
        return self.constraint.bounds

    # ---- the objective -----------------------------------------------------------------------

    def _free(self) -> bool:
        """Whether anything but ψ is learned (else a point is a smoothing at fixed θ)."""
        return int(np.size(self.points[0].theta)) > 1

    def _objective(self, theta, states, *, smooth: bool) -> tuple[float, Any]:
        """(objective, states) at θ: J from the states (smoothed first if asked) or evidence."""
        problem = self.problem
        if self.evidence:
            post = gaussian_posterior(self.smoother, problem.build(theta), states, problem.data)
            if np.any(np.asarray(post.status == RESULTS.nonfinite)[self.ok_weights]):
                return math.nan, states
            per = np.asarray(post.log_evidence, np.float64)
            return self._total(per) + self._log_prior(theta), post.states
        if smooth:
            sol = smooth_prepared(
                problem.build(theta), problem.data, states, self.smoother, runs=self.runs
            )
            if np.any(np.asarray(sol.status == RESULTS.nonfinite)[self.ok_weights]):
                return math.nan, states
            states = sol.states
        per = np.asarray(trajectory_log_likelihood(problem, theta, states), np.float64)
        return self._total(per) + self._log_prior(theta), states

    def _total(self, per: np.ndarray) -> float:
        return float(np.sum(np.where(self.ok_weights, per, 0.0)))

    def _log_prior(self, theta) -> float:
        if self.problem.log_prior is None:
            return 0.0
        return -float(self.problem.neg_log_prior(theta))

    def _refit(self, problem: FitProblem, theta, states):
        """The solver's epochs on ``problem`` from (θ, x): its last state."""
        solver = self.solver
        solver.check_problem(problem, theta)
        state = solver.init(problem, theta, states, jax.random.PRNGKey(0))
        for _ in range(self.max_epochs):
            before = state
            state, record = solver.step(problem, state)
            stop, _ = solver.terminate(problem, before, state, record)
            if stop:
                break
        state = solver.postprocess(problem, state)
        if np.any((np.asarray(state.weights) <= 0)[self.ok_weights]):
            raise _Failed("a trajectory failed in a refit")
        return state

    def _polish(self) -> None:
        """The maximum the profile falls from, refitted from the fit's end point (``polish``)."""
        start = self.points[0]
        self.evaluations += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if self.polish == "held":
                    theta, states = self._held(start, self.z_hat, self.estimate)
                else:
                    state = self._refit(self.problem, start.theta, start.states)
                    theta, states = state.theta, state.states
                value, _ = self._objective(theta, states, smooth=False)
        except (_Failed, ValueError, FloatingPointError):
            return
        if np.isfinite(value) and value > self.maximum:
            self.maximum = value
        if np.isfinite(value) and 2.0 * (value - start.value) > NOTED_RISE:
            self.notes.append(
                f"the fit's end point was not the maximum of the objective: a refit raised it by "
                f"{value - start.value:.3g}; the profile falls from there"
            )

    def value_at(self, z: float) -> float:
        """The profile's objective at ψ = forward(z) (a refit, warm-started; kept)."""
        for p in self.points:
            if p.z == z:
                return p.value
        start = min(self.points, key=lambda p: abs(p.z - z) if np.isfinite(p.value) else np.inf)
        x = self.natural(z)
        self.evaluations += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                theta, states = self._held(start, z, x)
                value, states = self._objective(theta, states, smooth=not self._free())
        except (_Failed, ValueError, FloatingPointError):
            theta, states, value = start.theta, start.states, math.nan
        self.points.append(_Point(z, value, theta, states))
        if np.isfinite(value) and value > self.maximum:
            if 2.0 * (value - self.points[0].value) > NOTED_RISE:
                self.notes.append(
                    f"the profile at {self.name} = {x:.6g} is above the fit's end point by "
                    f"{value - self.points[0].value:.3g}: the fit was not at the maximum; the "
                    "profile falls from the highest point found"
                )
            self.maximum = value
        return value

    def _held(self, start: _Point, z: float, x: float):
        """(θ, states) of the refit with ψ held at x, from ``start``."""
        problem = self.problem
        z_in = float(self.unconstrained(x))
        if not self._free():
            return jnp.asarray(np.asarray(start.theta).copy()).at[self.j].set(z_in), start.states
        if self.mask is None:  # an entry of an array: in θ, its transform without a gradient
            constraints = list(problem.constraints or [Unconstrained()] * (self.leaf + 1))
            constraints[self.leaf] = _HeldEntry(constraints[self.leaf], self.offset)
            held = FitProblem(
                problem.template, problem.static, problem.data, problem.log_prior,
                tuple(constraints),
            )  # fmt: skip
            state = self._refit(held, jnp.asarray(start.theta).at[self.j].set(z_in), start.states)
            theta = state.theta
        else:
            system = problem.build(start.theta)
            leaves, treedef = jtu.tree_flatten(system, is_leaf=_none)
            old = leaves[self.position]
            leaves[self.position] = jnp.full(jnp.shape(old), x, jnp.result_type(old))
            flags = list(self.mask)
            flags[self.position] = False
            held, theta0 = FitProblem.create(
                jtu.tree_unflatten(treedef, leaves),
                problem.data,
                trainable=jtu.tree_unflatten(treedef, flags),
                log_prior=problem.log_prior,
            )
            state = self._refit(held, theta0, start.states)
            theta = problem.theta_of(held.build(state.theta))
        if not bool(jnp.all(jnp.isfinite(theta))):
            raise _Failed("a refit returned a non-finite θ")
        return theta, state.states

    def drop(self, value: float) -> float:
        return 2.0 * (self.maximum - value)

    # ---- the search --------------------------------------------------------------------------

    @property
    def half_width(self) -> float:
        """q·σ_z, or 10 % of |ẑ| (at least 0.1) without a Wald interval."""
        if np.isfinite(self.sigma_z) and self.sigma_z > 0:
            return self.q * self.sigma_z
        return 0.1 * max(abs(self.z_hat), 1.0)

    def wald_end(self, side: int) -> float:
        return self.z_hat + side * self.half_width

    def screen(self, covariance: np.ndarray) -> list[float]:
        """√(2·drop)/q at the two Wald ends along the covariance's regression line (no refit).

        θ moves as the quadratic model's conditional maximiser, θ̂ + Σ_{·j}/Σ_jj·(z − ẑ), the
        states are smoothed (or the evidence evaluated) there: exact where the objective is
        quadratic (ratio 1), a lower bound of the profile elsewhere — a ratio below 1 means a
        profile flatter than the quadratic, above 1 a steeper one or a curved path.
        """
        c = np.asarray(covariance, np.float64)
        beta = np.where(np.isfinite(c[:, self.j]), c[:, self.j], 0.0) / c[self.j, self.j]
        theta = np.asarray(self.points[0].theta, np.float64)
        states = self.points[0].states
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref, _ = self._objective(self.points[0].theta, states, smooth=True)
            out = []
            for side in (-1, 1):
                guess = jnp.asarray(theta + beta * side * self.half_width, self.dtype)
                value, _ = self._objective(guess, states, smooth=True)
                d = 2.0 * (ref - value)
                out.append(math.sqrt(d) / self.q if np.isfinite(d) and d >= 0 else math.nan)
        return out

    def side(self, side: int, max_steps: int, xtol: float) -> tuple[float, End]:
        """The interval's end on ``side`` (−1 lower, +1 upper) and how it was found."""
        bound = self.bounds[0 if side < 0 else 1]
        z_near = None
        if np.isfinite(bound):
            x_near = bound + BOUND_GAP * (self.estimate - bound)
            z_near = self.unconstrained(x_near)
        q2 = self.q**2
        z_in = self.z_hat
        for k in range(max_steps):
            z = self.z_hat + side * self.half_width * 2.0**k
            last = False
            if z_near is not None and (k >= 2 or side * (z - z_near) >= 0):
                z, last = z_near, True
            value = self.value_at(z)
            if not np.isfinite(value):
                return math.nan, "failed"
            if self.drop(value) >= q2:
                return self._cross(z_in, z, xtol)
            if last:
                return float(bound), "bound"
            z_in = z
        return self.natural(z_in), "limit"

    def _cross(self, z_in: float, z_out: float, xtol: float) -> tuple[float, End]:
        """Brent's method on √(2·drop) − q between a point inside and one outside."""
        a, b = self.natural(z_in), self.natural(z_out)

        def g(x: float) -> float:
            if x == a:
                z = z_in
            elif x == b:
                z = z_out
            else:
                z = self.unconstrained(x)
            d = self.drop(self.value_at(z))
            if not np.isfinite(d):
                raise _Failed("a refit failed inside the bracket")
            return math.sqrt(max(d, 0.0)) - self.q

        slope = float(self.problem.natural_jacobian(self.points[0].theta)[self.j])
        scale = abs(slope) * self.half_width  # the Wald half-width in natural units
        tol = xtol * (scale if np.isfinite(scale) and scale > 0 else abs(b - a))
        try:
            sol = root_scalar(g, bracket=(a, b), method="brentq", xtol=tol, rtol=1e-12, maxiter=40)
        except (_Failed, ValueError, RuntimeError):
            return math.nan, "failed"
        return (float(sol.root), "found") if sol.converged else (math.nan, "failed")

    def wald(self) -> tuple[float, float]:
        ends = sorted(self.natural(self.wald_end(s)) for s in (-1, 1))
        if not (np.isfinite(self.sigma_z) and self.sigma_z > 0):
            return (math.nan, math.nan)
        return (ends[0], ends[1])

    def run(self, max_steps: int, xtol: float, grid: int = 0) -> Profile:
        """Both ends, after the polishing refit where the fit is not the refits' maximum.

        ``grid`` more points, evenly spaced in natural units over the interval and a quarter of
        its width beyond each end found (inside the bounds), for a figure.
        """
        if self.polish:
            self._polish()
            self.polish = ""
        lower, lower_end = self.side(-1, max_steps, xtol)
        upper, upper_end = self.side(+1, max_steps, xtol)
        if grid > 0 and np.isfinite(lower) and np.isfinite(upper):
            pad = 0.25 * (upper - lower)
            lo = lower - pad * (lower_end == "found")
            hi = upper + pad * (upper_end == "found")
            for x in np.linspace(lo, hi, grid + 2)[1:-1]:
                if self.bounds[0] < x < self.bounds[1]:
                    self.value_at(self.unconstrained(float(x)))
        pts = sorted(
            (self.natural(p.z), self.drop(p.value) if np.isfinite(p.value) else math.nan)
            for p in self.points
        )
        failed = sum(1 for p in self.points if not np.isfinite(p.value))
        notes = list(self.notes)
        if failed:
            notes.append(f"{failed} refits failed (non-finite objective or a trajectory lost)")
        return Profile(
            self.name,
            self.estimate,
            lower,
            upper,
            lower_end,
            upper_end,
            self.wald(),
            self.level,
            self.objective,
            tuple((float(v), float(d)) for v, d in pts),
            self.evaluations,
            time.perf_counter() - self.t0,
            tuple(dict.fromkeys(notes)),
        )


def _refit_solver(fitted: AbstractFitSolver, given, dtype) -> tuple[AbstractFitSolver, bool]:
    """(the refits' solver, whether it is the fit's method): ``given``, else module notes.

    A JointLM's identifiability check is off in the refits: an entry held by :class:`_HeldEntry`
    is a direction the data do not determine by construction.
    """
    same = given is None
    if given is not None:
        solver = given
    elif fitted.uncertainty == "evidence":
        solver = fitted
        if getattr(fitted, "coarse_start", None) is not None:
            solver = dataclasses.replace(fitted, coarse_start=None)
    elif isinstance(fitted, JointLM):
        solver = fitted
    else:
        solver, same = JointLM(), False
    if isinstance(solver, JointLM) and solver.check_identifiability:
        solver = dataclasses.replace(solver, check_identifiability=False)
    return trace_numbers(solver, dtype), same


def _none(v) -> bool:
    return v is None


def _locate(problem: FitProblem, j: int) -> tuple[int, int, int, list[bool] | None]:
    """(template leaf, offset in it, position among the system's leaves, the trainable flags).

    The flags (over the system's leaves) are ``None`` when the leaf holds more than one entry
    (the entry is then held by :class:`_HeldEntry`, not left out of θ).
    """
    leaves = jtu.tree_leaves(problem.template)
    sizes = np.cumsum([int(np.size(a)) for a in leaves])
    leaf = int(np.searchsorted(sizes, j, side="right"))
    offset = j - (int(sizes[leaf - 1]) if leaf else 0)
    mask = jtu.tree_map(lambda v: v is not None, problem.template, is_leaf=lambda v: v is None)
    system = eqx.combine(problem.template, problem.static)  # the system's structure
    flags = jtu.tree_leaves(mask, is_leaf=_none)
    if len(flags) != len(jtu.tree_leaves(system, is_leaf=_none)):
        raise ValueError("the fit problem's trainable split does not match its system")
    positions = [i for i, f in enumerate(flags) if f]
    whole = int(np.size(leaves[leaf])) == 1
    return leaf, offset, positions[leaf], ([bool(f) for f in flags] if whole else None)


class _HeldEntry(AbstractConstraint):
    """``base`` with entry ``index`` (flat) read through ``stop_gradient``: held where it is."""

    base: AbstractConstraint
    index: int = eqx.field(static=True)

    def forward(self, z):
        """``base.forward`` of z with entry ``index`` cut from the gradient."""
        flat = jnp.ravel(z)
        flat = flat.at[self.index].set(jax.lax.stop_gradient(flat[self.index]))
        return self.base.forward(flat.reshape(jnp.shape(z)))

    def inverse(self, x):
        """``base.inverse``."""
        return self.base.inverse(x)

    def contains(self, x):
        """``base.contains``."""
        return self.base.contains(x)

    @property
    def description(self) -> str:
        """``base``'s."""
        return self.base.description

    @property
    def bounds(self) -> tuple[float, float]:
        """``base``'s."""
        return self.base.bounds


def _index(problem: FitProblem, name: str) -> int:
    names = problem.parameter_names()
    key = name[1:] if name.startswith(".") and name[1:] in names else name
    if key not in names:
        raise KeyError(
            f"no trainable parameter named {name!r}; the fit's parameters are "
            f"{', '.join(names[:12])}{', …' if len(names) > 12 else ''}."
        )
    return names.index(key)


def _covariance(result, covariance) -> tuple[np.ndarray, np.ndarray, list[str]]:
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
        solver: the refits' solver (default: module notes).
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
    _, sigma, notes = _covariance(result, covariance)
    profiler = _Profiler(result, j, float(sigma[j]), level, max_epochs, solver)
    profiler.notes += notes
    return profiler.run(max_steps, xtol, grid)


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

    ``mode="profile"``: every parameter with a Wald interval. ``"auto"``: the rule of the module
    notes (a bound within 1.5 Wald half-widths; a profile skewed at the Wald ends), at most
    ``max_profiles`` parameters, the skewness checked on at most ``max_checks``; nothing for a
    fit that did not converge (its end point is not the maximum the profile falls from: each
    profile would first finish the fit — :meth:`ceemx.FitResult.profile` does).
    """
    problem, theta, _, _ = end_point(result)
    names = problem.parameter_names()
    if mode == "auto" and not result.converged:
        return {}, [
            "Intervals: Wald; no profile-likelihood interval, since the fit did not converge (a "
            "profile falls from the objective's maximum; FitResult.profile(name) refits to it "
            "first)."
        ]
    cov, sigma, _ = _covariance(result, covariance)
    nat = np.asarray(problem.natural(theta), np.float64)
    se = np.abs(np.asarray(problem.natural_jacobian(theta), np.float64)) * sigma
    q = NormalDist().inv_cdf(0.5 + level / 2.0)
    has = [j for j in range(len(names)) if np.isfinite(sigma[j])]
    profilers: dict[int, _Profiler] = {}

    def profiler(j: int) -> _Profiler:
        if j not in profilers:
            profilers[j] = _Profiler(result, j, float(sigma[j]), level, 50, None)
        return profilers[j]

    reasons: dict[int, str] = {}
    checked = unchecked = 0
    if mode == "profile":
        reasons = {j: "asked" for j in has}
    else:
        bounds = _entry_bounds(problem)
        for j in has:
            lo, hi = bounds[j]
            if nat[j] - NEAR_BOUND * q * se[j] <= lo or nat[j] + NEAR_BOUND * q * se[j] >= hi:
                reasons[j] = "near its bound"
        rest = sorted(
            (j for j in has if j not in reasons),
            key=lambda j: -se[j] / max(abs(nat[j]), 1e-300),
        )
        unchecked = max(len(rest) - max_checks, 0)
        for j in rest[:max_checks]:
            checked += 1
            try:
                ratios = profiler(j).screen(cov)
            except ValueError:
                continue
            if any(not np.isfinite(r) or r < 1.0 - SKEW for r in ratios):
                reasons[j] = (
                    "skewed: √(2·drop)/q = "
                    + " and ".join(f"{r:.3g}" for r in ratios)
                    + " at the Wald ends, not 1"
                )
        order = sorted(reasons, key=lambda j: (reasons[j] != "near its bound", j))
        reasons = {j: reasons[j] for j in order[:max_profiles]}
    out: dict[int, Profile] = {}
    for j in reasons:
        try:
            out[j] = profiler(j).run(5, 1e-3)
        except ValueError:
            continue
    notes = []
    if mode == "auto":
        text = "Intervals: Wald (the quadratic model of the objective at the estimate)"
        if out:
            text += ", except the profile likelihood for " + ", ".join(
                f"{names[j]} ({reasons[j]})" for j in out
            )
        some = f"{checked} of {len(has)}, the most uncertain" if unchecked else "all"
        text += (
            f". Profiled when a bound lies within {NEAR_BOUND:g} Wald half-widths or "
            f"√(2·drop)/q at a Wald end is below {1 - SKEW:g} (skewness checked "
            f"on {some}), at most {max_profiles} parameters; summary(intervals='profile') "
            "profiles every one, FitResult.profile(name) one."
        )
        notes.append(text)
    elif out:
        notes.append(
            "Intervals: profile likelihood, "
            + ", ".join(f"{p.name} {p.evaluations} refits" for p in out.values())
        )
    return out, notes


def _entry_bounds(problem: FitProblem) -> list[tuple[float, float]]:
    leaves = jtu.tree_leaves(problem.template)
    constraints: Sequence[Any] = problem.constraints or [Unconstrained()] * len(leaves)
    out: list[tuple[float, float]] = []
    for c, leaf in zip(constraints, leaves, strict=True):
        out += [c.bounds] * int(np.size(leaf))
    return out
