"""The learning step's objective (paper Eq. 11) over a flat vector of the trainable parameters."""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, Float, Int

from ceemx.data.trajectories import Trajectories
from ceemx.identification.problem import FitProblem
from ceemx.inference.objective import linearize
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta
from ceemx.models.system import AbstractSystem

__all__ = ["AbstractLearningProblem", "LearningProblem", "make_problem"]


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
