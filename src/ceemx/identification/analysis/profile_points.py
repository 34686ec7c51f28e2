"""The points of a profile likelihood: the objective at one parameter held, the rest refitted.

:class:`ProfilePoints` computes, for entry ψ of a fit's θ
(:mod:`ceemx.identification.analysis.profile` searches with it), the objective the fit
maximised — J(x, θ) + log p(θ) for the certainty-equivalent methods, the Laplace log-evidence +
log p(θ) for :class:`ceemx.LaplaceEM` (solver flag ``uncertainty``) — maximised over the states
and the other parameters with ψ held at a value:

* the problem with ψ held: a ``trainable`` filter without ψ's leaf (``FitProblem.create``), or,
  for an entry of a larger array (which cannot leave θ on its own), the same problem with that
  leaf's constraint replaced by :class:`HeldEntry` — the entry stays in θ and its transform reads
  it through ``stop_gradient``, so its gradient and curvature are zero and no solver moves it
  (Marquardt's damping keeps such a direction still); exact either way, one compilation of the
  solver's programs per parameter, none per value;
* the refit: from the nearest point already computed (its θ and states), by the solver interface
  (``init``/``step``/``terminate``/``postprocess``, at most ``max_epochs`` epochs, the solver's
  tolerances) — as :func:`ceemx.fit` runs its epochs, without its per-call checks, warm start,
  health test and end-of-fit check (the inputs were checked by the fit, and
  :mod:`ceemx.identification.fitting` builds ``FitResult`` on these modules, so it cannot be
  called from here). The solver: Laplace EM's own (without its coarse start); for the
  certainty-equivalent methods the fit's own where it settles in a few epochs from a warm start
  (solver flag ``warm_refits``: :class:`ceemx.JointLM`), else a :class:`ceemx.JointLM` (the same J;
  Algorithm 1 would take many epochs to settle each point); a JointLM's identifiability check is
  off (a held entry is an undetermined direction by construction);
* the objective at the refit's end point exactly as at the fit's: J from the states, or the
  log-evidence from a MAP smoothing and the log-determinant of its Gauss–Newton matrix (the
  smoother of the fit's solver, as
  :func:`~ceemx.identification.analysis.uncertainty.evidence_covariance` does).

The maximum the profile falls from is the objective at the fit's end point; after a method other
than the refits' (Algorithm 1) the larger of it and a refit with ψ held at its estimate; after a
fit that did not converge, the larger of it and a refit with nothing held (the fit continued by
the refits' solver). A point above the maximum raises it (a note says so when by more than 0.01
in 2·Δ).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from statistics import NormalDist
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

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

__all__ = ["HeldEntry", "ProfilePoint", "ProfilePoints", "RefitFailed", "refit_solver"]

#: a rise of the objective above the fit's end point (in 2·Δ, the drop's units) worth a note
NOTED_RISE = 0.01


class RefitFailed(Exception):
    """A refit or an evaluation of the objective failed (non-finite, a trajectory lost)."""


@dataclasses.dataclass
class ProfilePoint:
    """One point: ψ's unconstrained z, the objective there (NaN: failed), the full θ, states."""

    z: float
    value: float
    theta: Any
    states: Any


class ProfilePoints:
    """The profile of entry ``j`` of a fit's θ: its points, computed on demand and kept.

    Each point is the objective at ψ = forward(z) maximised over the rest (module notes); the
    search (:mod:`ceemx.identification.analysis.profile`) asks for the points it needs.
    """

    def __init__(self, result, j: int, sigma_z: float, level: float, max_epochs: int, solver):
        """The profile of entry ``j`` of ``result``'s θ (σ_z: its Wald standard deviation)."""
        problem, theta, states, weights = end_point(result)
        self.problem, self.weights, self.j, self.dtype = problem, weights, j, theta.dtype
        self.name = problem.parameter_names()[j]
        self.level, self.q = level, NormalDist().inv_cdf(0.5 + level / 2.0)
        self.max_epochs = max_epochs
        self.evidence = result.solver.uncertainty == "evidence"
        self.objective_name = "Laplace evidence" if self.evidence else "certainty-equivalent J"
        self.solver, same = refit_solver(result.solver, solver, theta.dtype)
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
        value, states = self.objective(theta, states, smooth=False)
        self.points = [ProfilePoint(self.z_hat, value, theta, states)]
        self.maximum = value
        if not np.isfinite(value):
            raise ValueError(f"the objective is not finite at the fit's end point ({value}).")
        # the maximum: a converged fit of the refits' method is at it; one of another method
        # (Algorithm 1) is refitted with ψ held at its estimate (the refits' own program); one
        # that did not converge is refitted with nothing held
        self.polish = "" if not self.free() or (result.converged and same) else "held"
        if not result.converged and self.free():
            self.polish = "free"

    # ---- coordinates -------------------------------------------------------------------------

    def natural(self, z: float) -> float:
        """ψ in natural units at the unconstrained z."""
        return float(self.constraint.forward(jnp.asarray(z, self.dtype)))

    def unconstrained(self, x: float) -> float:
        """The unconstrained z of ψ = x."""
        return float(self.constraint.inverse(jnp.asarray(x, self.dtype)))

    @property
    def bounds(self) -> tuple[float, float]:
        """ψ's constraint's (lower, upper)."""
        return self.constraint.bounds

    # ---- the objective -----------------------------------------------------------------------

    def free(self) -> bool:
        """Whether anything but ψ is learned (else a point is a smoothing at fixed θ)."""
        return int(np.size(self.points[0].theta)) > 1

    def objective(self, theta, states, *, smooth: bool) -> tuple[float, Any]:
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
            raise RefitFailed("a trajectory failed in a refit")
        return state

    def polish_maximum(self) -> None:
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
                value, _ = self.objective(theta, states, smooth=False)
        except (RefitFailed, ValueError, FloatingPointError):
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
                value, states = self.objective(theta, states, smooth=not self.free())
        except (RefitFailed, ValueError, FloatingPointError):
            theta, states, value = start.theta, start.states, math.nan
        self.points.append(ProfilePoint(z, value, theta, states))
        if np.isfinite(value) and value > self.maximum:
            if 2.0 * (value - self.points[0].value) > NOTED_RISE:
                self.notes.append(
                    f"the profile at {self.name} = {x:.6g} is above the fit's end point by "
                    f"{value - self.points[0].value:.3g}: the fit was not at the maximum; the "
                    "profile falls from the highest point found"
                )
            self.maximum = value
        return value

    def _held(self, start: ProfilePoint, z: float, x: float):
        """(θ, states) of the refit with ψ held at x, from ``start``."""
        problem = self.problem
        z_in = float(self.unconstrained(x))
        if not self.free():
            return jnp.asarray(np.asarray(start.theta).copy()).at[self.j].set(z_in), start.states
        if self.mask is None:  # an entry of an array: in θ, its transform without a gradient
            constraints = list(problem.constraints or [Unconstrained()] * (self.leaf + 1))
            constraints[self.leaf] = HeldEntry(constraints[self.leaf], self.offset)
            held = FitProblem(
                problem.template, problem.static, problem.data, problem.log_prior,
                tuple(constraints), problem.overrides,
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
                overrides=problem.overrides,
            )
            state = self._refit(held, theta0, start.states)
            theta = problem.theta_of(held.build(state.theta))
        if not bool(jnp.all(jnp.isfinite(theta))):
            raise RefitFailed("a refit returned a non-finite θ")
        return theta, state.states

    def drop(self, value: float) -> float:
        """2·(maximum − value)."""
        return 2.0 * (self.maximum - value)

    @property
    def half_width(self) -> float:
        """q·σ_z, or 10 % of |ẑ| (at least 0.1) without a Wald interval."""
        if np.isfinite(self.sigma_z) and self.sigma_z > 0:
            return self.q * self.sigma_z
        return 0.1 * max(abs(self.z_hat), 1.0)

    def wald_end(self, side: int) -> float:
        """ẑ ± q·σ_z (side −1 or +1)."""
        return self.z_hat + side * self.half_width

    def wald(self) -> tuple[float, float]:
        """The Wald interval ``forward(ẑ ± q·σ_z)`` (NaN without σ_z)."""
        ends = sorted(self.natural(self.wald_end(s)) for s in (-1, 1))
        if not (np.isfinite(self.sigma_z) and self.sigma_z > 0):
            return (math.nan, math.nan)
        return (ends[0], ends[1])


def refit_solver(fitted: AbstractFitSolver, given, dtype) -> tuple[AbstractFitSolver, bool]:
    """(the refits' solver, whether it is the fit's method): ``given``, else module notes.

    A JointLM's identifiability check is off in the refits: an entry held by :class:`HeldEntry`
    is a direction the data do not determine by construction.
    """
    same = given is None
    if given is not None:
        solver = given
    elif fitted.uncertainty == "evidence":
        solver = fitted
        if getattr(fitted, "coarse_start", None) is not None:
            solver = dataclasses.replace(fitted, coarse_start=None)
    elif fitted.warm_refits:
        solver = fitted
    else:
        solver, same = JointLM(), False
    if getattr(solver, "check_identifiability", False):
        solver = dataclasses.replace(solver, check_identifiability=False)
    return trace_numbers(solver, dtype), same


def _none(v) -> bool:
    return v is None


def _locate(problem: FitProblem, j: int) -> tuple[int, int, int, list[bool] | None]:
    """(template leaf, offset in it, position among the system's leaves, the trainable flags).

    The flags (over the system's leaves) are ``None`` when the leaf holds more than one entry
    (the entry is then held by :class:`HeldEntry`, not left out of θ).
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


class HeldEntry(AbstractConstraint):
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
