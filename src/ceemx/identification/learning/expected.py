"""Laplace EM's M-step objective: −Q(θ) = E_q[−log p(x, y | θ)] under a Gaussian state posterior.

q is the Laplace approximation N(x̂, Σ̂) of each trajectory's state posterior (the MAP trajectory
and the inverse Gauss–Newton matrix of −J at it). −log p(x, y | θ) is a sum of factors that touch
one state x_t (observations, the initial prior) or a pair (x_t, x_{t+1}) (dynamics), so Q needs
only the marginals N(x̂_t, Σ̂_t) and the pairwise marginals of (x_t, x_{t+1}) — the diagonal and
sub-diagonal blocks of the selected inverse. Each expectation is taken by the third-degree
spherical–radial cubature rule (:mod:`ceemx.lib.cubature`): 2n points per marginal, 4n per pair.

Why cubature and not linearisation with trace terms: both are exact when the model is linear in
x (the rule integrates quadratics exactly, so Laplace EM *is* EM on linear-Gaussian models), but
cubature also integrates the cubic terms of a nonlinear model exactly (the bilinear terms of the
Lorenz field, a Duffing spring), it needs only first derivatives of f and g in θ for the
Gauss–Newton matrix (trace terms would need ∂²f/∂x∂θ), and it applies to any noise density, not
only Gaussian ones. Tested against Monte Carlo over q in ``tests/test_laplace_em.py``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ceemx.identification.learning.learning_problem import AbstractLearningProblem
from ceemx.identification.problem import FitProblem
from ceemx.inference.objective import expected_neg_log_joint_single, linearize_expected
from ceemx.infra.compilation import jit
from ceemx.lib.cubature import pair_covariances, sigma_points
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta

__all__ = ["ExpectedLearningProblem", "cubature_points", "expected_learning_problem"]


class ExpectedLearningProblem(AbstractLearningProblem):
    """min_θ Σ_b w_b E_q[−log p(x_b, y_b | θ)] + ρ_θ‖θ − θ_ref‖² − log p(θ)  (Laplace EM's M-step).

    Attributes:
        problem: the identification problem (data, θ split, prior).
        points: (B, T, 2n, n) cubature points of each marginal q(x_t).
        pairs: (B, T−1, 4n, 2n) cubature points of each pairwise marginal q(x_t, x_{t+1}).
        weights: (B,) trajectory weights (0 excludes one).
        theta_ref: θᵏ, the centre of the trust region.
        rho_theta: ρ_θ.
    """

    problem: FitProblem
    points: Float[Array, "B T K n"]
    pairs: Float[Array, "B T-1 K2 n2"]
    weights: PerTrajectory
    theta_ref: Theta
    rho_theta: Scalar

    def per_trajectory(self, theta: Theta, idx: Int[Array, " _"] | None = None) -> PerTrajectory:
        """E_q[−log p(x_b, y_b | θ)] of the trajectories ``idx`` (all when ``None``)."""
        points, pairs, data = self.participating(self.points, self.pairs, self.data)
        if idx is not None:
            points, pairs, data = points[idx], pairs[idx], data[idx]
        system = self.build(theta)
        return jax.vmap(expected_neg_log_joint_single, in_axes=(None, 0, 0, 0, 0, 0))(
            system, points, pairs, data.y, data.u, data.mask
        )

    def per_trajectory_gauss_newton(
        self, theta: Theta
    ) -> tuple[PerTrajectory, Float[Array, "B theta"], Float[Array, "B theta theta"]]:
        """Per trajectory: the expected −log p, its θ-gradient and Gauss–Newton matrix."""
        data = self.data
        return jax.vmap(
            lambda xp, zp, y, u, m: linearize_expected(self.build, theta, xp, zp, y, u, m)
        )(self.points, self.pairs, data.y, data.u, data.mask)


@jit
def cubature_points(
    states: States, covariances: Float[Array, "B T n n"], cross: Float[Array, "B T-1 n n"]
) -> tuple[Float[Array, "B T K n"], Float[Array, "B T-1 K2 n2"]]:
    """Marginal and pairwise cubature points of the Gaussians N(x̂, Σ̂) given by their blocks."""
    points = sigma_points(states, covariances)
    pair_means = jnp.concatenate([states[:, :-1], states[:, 1:]], axis=-1)
    pair_cov = jax.vmap(pair_covariances)(covariances, cross)
    return points, sigma_points(pair_means, pair_cov)


def expected_learning_problem(
    problem: FitProblem,
    theta: Theta,
    states: States,
    covariances: Float[Array, "B T n n"],
    cross: Float[Array, "B T-1 n n"],
    weights: PerTrajectory,
    rho_theta: Scalar | float = 0.0,
) -> ExpectedLearningProblem:
    """The M-step objective at θ for the posteriors N(x̂, Σ̂) given by their blocks."""
    points, pairs = cubature_points(states, covariances, cross)
    rho = jnp.asarray(rho_theta, states.dtype)
    return ExpectedLearningProblem(
        problem=problem, points=points, pairs=pairs, weights=weights, theta_ref=theta, rho_theta=rho
    )
