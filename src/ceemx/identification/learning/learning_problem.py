"""The learning step's objective (paper Eq. 11) over a flat vector of the trainable parameters."""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float, Int

from ceemx.data.trajectories import Trajectories
from ceemx.identification.learning.gauss_newton import batch_gauss_newton
from ceemx.identification.problem import FitProblem
from ceemx.inference.objective import linearize
from ceemx.infra.options import check_int
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta
from ceemx.models.system import AbstractSystem

__all__ = [
    "AbstractLearningProblem",
    "LearningProblem",
    "WindowedLearningProblem",
    "make_problem",
    "window_starts",
    "windowed",
]


class AbstractLearningProblem(eqx.Module):
    """min_θ Σ_b w_b ℓ_b(θ) + ρ_θ‖θ − θ_ref‖² − log p(θ): what every learner minimises.

    A subclass says what the per-trajectory loss ℓ_b is — :class:`LearningProblem`: −J_b(x_b, θ) at
    fixed states (Eq. 11; CE-EM, SAEM);
    :class:`ceemx.identification.learning.ExpectedLearningProblem`:
    E_q[−log p(x_b, y_b | θ)] under a Gaussian state posterior q (Laplace EM) — by implementing
    :meth:`per_trajectory` and :meth:`per_trajectory_gauss_newton`; the weighting, the trust
    region, the prior, minibatches and the Gauss–Newton assembly are shared.

    Attributes:
        problem: the identification problem (data, θ split, prior).
        weights: (B,) non-negative weights w_b; 0 excludes a trajectory (e.g. failed smoothing).
        theta_ref: θᵏ, the centre of the trust region.
        rho_theta: ρ_θ.
    """

    problem: eqx.AbstractVar[FitProblem]
    weights: eqx.AbstractVar[PerTrajectory]
    theta_ref: eqx.AbstractVar[Theta]
    rho_theta: eqx.AbstractVar[Scalar]

    @abc.abstractmethod
    def per_trajectory(self, theta: Theta, idx: Int[Array, " _"] | None = None) -> PerTrajectory:
        """ℓ_b(θ) of the trajectories ``idx`` (all when ``None``); excluded ones finite."""

    @abc.abstractmethod
    def per_trajectory_gauss_newton(
        self, theta: Theta
    ) -> tuple[PerTrajectory, Float[Array, "B theta"], Float[Array, "B theta theta"]]:
        """Per trajectory: ℓ_b, its θ-gradient and its Gauss–Newton matrix."""

    @property
    def batch_size(self) -> int:
        """Number of trajectories (minibatches draw from these)."""
        return self.weights.shape[0]

    @property
    def data(self) -> Trajectories:
        """The observations."""
        return self.problem.data

    def build(self, theta: Theta) -> AbstractSystem:
        """The system with trainable leaves set from the flat vector θ."""
        return self.problem.build(theta)

    def regulariser(self, theta: Theta) -> Scalar:
        """ρ_θ‖θ − θ_ref‖² − log p(θ): the objective's terms that do not involve the data."""
        d = theta - self.theta_ref
        return self.rho_theta * jnp.sum(d**2) + self.problem.neg_log_prior(theta)

    def participating(self, *arrays):
        """``arrays`` (leading axis B) with each excluded trajectory replaced by a taking-part one.

        Excluded trajectories (weight 0, e.g. failed smoothing) can have non-finite terms; masking
        their values with ``jnp.where`` is not enough under differentiation (0·∞ = NaN in the
        gradient), so their inputs are swapped for finite ones before evaluation.
        """
        ok = self.weights > 0
        ref = jnp.argmax(ok)

        def pick(a):
            return jnp.where(ok.reshape((-1,) + (1,) * (a.ndim - 1)), a, a[ref][None])

        return jtu.tree_map(pick, arrays)

    def data_term(self, theta: Theta) -> Scalar:
        """Σ_b w_b ℓ_b(θ): the objective without the trust region and the prior."""
        nll = self.per_trajectory(theta)
        return jnp.sum(jnp.where(self.weights > 0, self.weights * nll, 0.0))

    def value(self, theta: Theta) -> Scalar:
        """The learning objective (scalar)."""
        return self.data_term(theta) + self.regulariser(theta)

    def minibatch_value(self, theta: Theta, idx: Int[Array, " _"]) -> Scalar:
        """Unbiased estimate of :meth:`value` from the trajectories ``idx``."""
        w = self.weights[idx]
        nll = self.per_trajectory(theta, idx)
        part = jnp.sum(w)
        scale = jnp.where(part > 0, jnp.sum(self.weights) / jnp.where(part > 0, part, 1.0), 0.0)
        return scale * jnp.sum(jnp.where(w > 0, w * nll, 0.0)) + self.regulariser(theta)

    def offset(self, theta: Theta) -> Scalar:
        """The x-independent constants of the objective (see :meth:`FitProblem.offset`)."""
        return self.problem.offset(theta, self.weights)

    def gauss_newton(
        self, theta: Theta
    ) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "theta theta"]]:
        """(value, gradient, Gauss–Newton matrix) of the objective at θ."""
        values, grads, Ds = self.per_trajectory_gauss_newton(theta)
        ok = self.weights > 0
        w = self.weights
        d = theta - self.theta_ref
        prior, prior_grad, prior_hess = self.problem.prior_terms(theta)
        value = jnp.sum(jnp.where(ok, w * values, 0.0)) + self.rho_theta * jnp.sum(d**2) + prior
        grad = jnp.sum(jnp.where(ok[:, None], w[:, None] * grads, 0.0), axis=0)
        grad = grad + 2.0 * self.rho_theta * d + prior_grad
        hess = jnp.sum(jnp.where(ok[:, None, None], w[:, None, None] * Ds, 0.0), axis=0)
        hess = hess + prior_hess
        hess = hess + 2.0 * self.rho_theta * jnp.eye(theta.shape[0], dtype=theta.dtype)
        return value, grad, hess


class LearningProblem(AbstractLearningProblem):
    """min_θ Σ_b w_b (−J_b(x_b, θ)) + ρ_θ‖θ − θ_ref‖² − log p(θ)  (Eq. 11), θ the trainable leaves.

    The weights are 1 for trajectories taking part and 0 for excluded ones in CE-EM; other
    non-negative weights make the objective a weighted sum (SAEM's Q̂ over stored samples).

    Attributes:
        problem: the identification problem (data, θ split, prior).
        states: (B, T, n) fixed state trajectories.
        weights: (B,) non-negative weights w_b; 0 excludes a trajectory (e.g. failed smoothing).
        theta_ref: θᵏ, the centre of the trust region.
        rho_theta: ρ_θ.
    """

    problem: FitProblem
    states: States
    weights: PerTrajectory
    theta_ref: Theta
    rho_theta: Scalar

    def per_trajectory(self, theta: Theta, idx: Int[Array, " _"] | None = None) -> PerTrajectory:
        """−J_b(x_b, θ) of the trajectories ``idx`` (all when ``None``)."""
        states, data = self.participating(self.states, self.data)
        if idx is not None:
            states, data = states[idx], data[idx]
        return self.problem.per_trajectory(theta, states, data)

    def per_trajectory_gauss_newton(
        self, theta: Theta
    ) -> tuple[PerTrajectory, Float[Array, "B theta"], Float[Array, "B theta theta"]]:
        """Per trajectory: −J_b, its θ-gradient and its Gauss–Newton matrix (states fixed)."""
        data = self.data
        lin = jax.vmap(
            lambda x, y, u, m: linearize(self.build, theta, x, y, u, m, wrt_theta=True, wrt_x=False)
        )(self.states, data.y, data.u, data.mask)
        assert lin.grad_theta is not None and lin.D is not None  # wrt_theta=True
        return lin.value, lin.grad_theta, lin.D

    def gauss_newton(
        self, theta: Theta
    ) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "theta theta"]]:
        """(value, gradient, Gauss–Newton matrix) of the objective at θ.

        The same matrix as :meth:`AbstractLearningProblem.gauss_newton`, formed from every
        taking-part trajectory's whitened θ-Jacobian rows scaled by √w_b, a chunk of time steps at
        a time (:func:`~ceemx.identification.learning.gauss_newton.batch_gauss_newton`): P × P
        products of a few MB of rows instead of one per trajectory or one of all rows, and no rows
        for factors that do not depend on θ.
        """
        data = self.data
        value, grad, hess = batch_gauss_newton(
            self.build, theta, self.states, data.y, data.u, data.mask, self.weights
        )
        d = theta - self.theta_ref
        prior, prior_grad, prior_hess = self.problem.prior_terms(theta)
        value = value + self.rho_theta * jnp.sum(d**2) + prior
        grad = grad + 2.0 * self.rho_theta * d + prior_grad
        hess = hess + prior_hess
        hess = hess + 2.0 * self.rho_theta * jnp.eye(theta.shape[0], dtype=theta.dtype)
        return value, grad, hess


def make_problem(
    system: AbstractSystem,
    states: States,
    data: Trajectories,
    *,
    trainable=None,
    rho_theta: float | Array = 0.0,
    log_prior=None,
    weights: PerTrajectory | None = None,
) -> tuple[LearningProblem, Theta]:
    """The :class:`LearningProblem` of ``system`` around its current θ, and that θ."""
    problem, theta = FitProblem.create(system, data, trainable=trainable, log_prior=log_prior)
    return learning_problem(problem, theta, states, weights, rho_theta), theta


def learning_problem(
    problem: FitProblem,
    theta: Theta,
    states: States,
    weights: PerTrajectory | None = None,
    rho_theta: float | Array = 0.0,
) -> LearningProblem:
    """The learning step of ``problem`` at θ with the states fixed."""
    states = jnp.asarray(states)
    B = states.shape[0]
    w = jnp.ones((B,), states.dtype) if weights is None else jnp.asarray(weights, states.dtype)
    return LearningProblem(
        problem=problem,
        states=states,
        weights=w,
        theta_ref=theta,
        rho_theta=jnp.asarray(rho_theta, states.dtype),
    )


def window_starts(T: int, length: int) -> np.ndarray:
    """Starts of windows of ``length`` transitions (``length + 1`` samples) covering T samples.

    Consecutive windows share one sample (the last of one is the first of the next); the last
    window ends at sample T − 1 and may overlap its predecessor by more.
    """
    if T < 2:
        raise ValueError(f"a record needs at least 2 samples to cut windows; got T = {T}.")
    check_int("window", length, 1)
    length = min(int(length), T - 1)
    starts = np.arange(0, T - 1, length)
    starts[-1] = min(starts[-1], T - 1 - length)
    return starts


class WindowedLearningProblem(AbstractLearningProblem):
    """:class:`LearningProblem` with every record cut into short windows of time (minibatches).

    At fixed states, −J is a sum of per-step terms, so cutting the (B, T) record into windows of
    L transitions and summing the windows' −J gives the record's −J exactly — each observation
    counted once (a sample shared by two windows is masked in one), each transition once except
    those of the last window that overlap its predecessor (at most L − 1 of T − 1), and the
    initial-state prior only in each record's first window. Minibatches of windows
    (:class:`~ceemx.identification.learning.learners.OptaxLearner` with ``batch_size``, through
    :class:`~ceemx.identification.learning.windowed.WindowedLearner`) are then minibatches of
    time, which a single long record (B = 1) otherwise cannot have.

    Attributes:
        problem: the identification problem.
        states: (B·W, L + 1, n) window states.
        windows: the (B·W, L + 1) window data (masks adjusted).
        weights: (B·W,) each window's record's weight.
        first: (B·W,) whether a window starts its record (carries the initial prior).
        theta_ref: θᵏ; rho_theta: ρ_θ.
    """

    problem: FitProblem
    states: States
    windows: Trajectories
    weights: PerTrajectory
    first: Array
    theta_ref: Theta
    rho_theta: Scalar

    @property
    def data(self) -> Trajectories:
        """The windows (what minibatches draw from)."""
        return self.windows

    def per_trajectory(self, theta: Theta, idx: Int[Array, " _"] | None = None) -> PerTrajectory:
        """−J of the windows ``idx`` (all when ``None``), the prior only in first windows."""
        states, data, first = self.participating(self.states, self.windows, self.first)
        if idx is not None:
            states, data, first = states[idx], data[idx], first[idx]
        values = self.problem.per_trajectory(theta, states, data)
        prior = self.build(theta).initial_prior
        if prior is not None:
            values = values - jnp.where(first, 0.0, jax.vmap(prior.nll)(states[:, 0]))
        return values

    def per_trajectory_gauss_newton(self, theta: Theta):
        """Not provided: windows are for first-order minibatch learners."""
        raise NotImplementedError(
            "a windowed learning problem is for first-order minibatch learners (OptaxLearner); "
            "use the LM learner on the whole record."
        )


def windowed(problem: LearningProblem, length: int) -> WindowedLearningProblem:
    """``problem`` with its records cut into windows of ``length`` transitions (see the class)."""
    B, T = problem.states.shape[:2]
    starts = window_starts(T, length)
    L = min(int(length), T - 1)
    idx = starts[:, None] + np.arange(L + 1)
    keep = np.ones(idx.shape, bool)  # each sample observed in one window only
    keep[:-1, -1] = False
    if len(starts) > 1:
        keep[-1] &= idx[-1] >= starts[-2] + L
    W = len(starts)
    data = problem.data

    def cut(a):
        return a[:, jnp.asarray(idx)].reshape((B * W, L + 1) + a.shape[2:])

    mask = cut(data.mask) & jnp.asarray(np.tile(keep, (B, 1)))[..., None]
    first = np.zeros((B, W), bool)
    first[:, 0] = True
    return WindowedLearningProblem(
        problem=problem.problem,
        states=cut(problem.states),
        windows=Trajectories(cut(data.y), cut(data.u), mask),
        weights=jnp.repeat(problem.weights, W),
        first=jnp.asarray(first.reshape(-1)),
        theta_ref=problem.theta_ref,
        rho_theta=problem.rho_theta,
    )
