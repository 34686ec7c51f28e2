"""Gaussian (Laplace) state posteriors at a fixed θ: N(x̂, Σ̂) around the MAP trajectory.

The MAP trajectory x̂ of each trajectory (the smoother, Eq. 10) and the inverse Gauss–Newton
matrix of −J at x̂: its marginal blocks Σ̂_t and lag-one blocks Cov(x_{t+1}, x_t) from the selected
inverse of the same block-tridiagonal factorisation (O(T n³)), and the Laplace log-evidence
log p(y | θ) ≈ J(x̂, θ) + (Tn/2) log 2π − ½ log det H. Laplace EM's E-step
(:mod:`ceemx.identification.solvers.laplace`) and the evidence covariance
(:mod:`ceemx.identification.analysis.uncertainty`) read it.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ceemx.data.trajectories import Trajectories
from ceemx.inference import smoother as smoothing_solver
from ceemx.infra.compilation import jit
from ceemx.lib.results import RESULTS, select
from ceemx.lib.typing import PerTrajectory, States
from ceemx.models.system import AbstractSystem

__all__ = ["E_STEP_SMOOTHER", "GaussianPosterior", "gaussian_posterior"]

# The E-step's MAP must be converged well past CE-EM's needs: the posterior mean and covariance
# are evaluated at it, and EM's convergence is measured in the change of the evidence. It starts
# from the previous E-step's MAP, so its first Gauss–Newton step is nearly exact: a small initial
# Marquardt damping (1e-6, not the smoother's 1e-3, which shrinks each step's progress to ~λ) takes
# 2–3 iterations instead of 6–7 to rtol 1e-14 (mass–spring–damper, T = 25 000; the same evidence
# to 10 digits); the damping still grows on a rejected step, so cold starts are unaffected.
E_STEP_SMOOTHER = smoothing_solver.LMSmoother(rtol=1e-14, damping=1e-6)


class GaussianPosterior(eqx.Module):
    """Laplace approximations N(x̂_b, Σ̂_b) of the state posteriors, and the log-evidence.

    Attributes:
        states: (B, T, n) MAP trajectories x̂.
        covariances: (B, T, n, n) marginal covariances Σ̂_t.
        cross: (B, T−1, n, n) Cov(x_{t+1}, x_t).
        log_evidence: (B,) Laplace approximation of log p(y_b | θ).
        status: (B,) :class:`ceemx.RESULTS` (``nonfinite`` where the posterior is not finite).
        iterations: (B,) smoother iterations.
    """

    states: States
    covariances: Float[Array, "B T n n"]
    cross: Float[Array, "B T-1 n n"]
    log_evidence: PerTrajectory
    status: RESULTS
    iterations: Array


@jit
def gaussian_posterior(
    smoother: smoothing_solver.LMSmoother, system: AbstractSystem, x0: States, data: Trajectories
) -> GaussianPosterior:
    """The Laplace approximation of every trajectory's state posterior at the system's θ.

    MAP smoothing from ``x0`` (compiled; numbers of ``smoother`` must be traced arrays, see
    :func:`ceemx.lib.trace_numbers`), then the selected inverse and log-determinant of the
    Gauss–Newton matrix at the MAP: means, marginal and lag-one covariances, and the Laplace
    log-evidence log p(y_b | θ) ≈ J_b(x̂_b, θ) + (Tn/2) log 2π − ½ log det H_b per trajectory.
    """
    sol = smoothing_solver.smooth_batch(smoother, system, x0, data, True)
    assert sol.covariances is not None and sol.cross_covariances is not None
    assert sol.log_det is not None
    T, n = x0.shape[1], x0.shape[2]
    log_ev = -sol.objective + 0.5 * T * n * math.log(2.0 * math.pi) - 0.5 * sol.log_det
    finite = (
        jnp.isfinite(log_ev)
        & jnp.all(jnp.isfinite(sol.covariances), axis=(1, 2, 3))
        & jnp.all(jnp.isfinite(sol.cross_covariances), axis=(1, 2, 3))
    )
    status = select(finite, sol.status, RESULTS.nonfinite)
    return GaussianPosterior(
        sol.states, sol.covariances, sol.cross_covariances, log_ev, status, sol.iterations
    )
