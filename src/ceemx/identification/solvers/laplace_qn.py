"""Quasi-Newton steps for Laplace EM: BFGS on the EM fixed-point equation ∇Q(θ | θ) = 0.

``LaplaceEM(acceleration="quasi_newton")`` (:mod:`ceemx.identification.solvers.laplace`) takes
one step per epoch along H⁻¹g: g the ascent gradient of the Laplace log-evidence (+ log-prior),
from the gradient of Q at θ (Fisher's identity; exact on models linear in the state), H⁻¹ a
BFGS inverse curvature started from the complete-data information −∇²Q (EM's metric). The pieces
here are the maths of those steps: the coordinates (log for the noise models' standard
deviations, :meth:`ceemx.AbstractNoise.scale_parameters`), the derivatives of Q, the start of the
curvature and the damped BFGS update.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ceemx.identification.learning.expected import ExpectedLearningProblem, cubature_points
from ceemx.identification.problem import FitProblem
from ceemx.inference.posterior import GaussianPosterior
from ceemx.infra.compilation import jit
from ceemx.lib.results import RESULTS
from ceemx.lib.typing import Theta

__all__ = [
    "QN_BACKTRACKS",
    "QN_EXPAND",
    "QN_MAX_PARAMETERS",
    "QN_MAX_STEP",
    "Coordinates",
    "bfgs_update",
    "log_prior_value",
    "q_derivatives",
    "qn_gradient",
    "qn_start",
]

#: the largest θ (entries) ``acceleration="quasi_newton"`` takes: its curvature is dense P × P
QN_MAX_PARAMETERS = 200
#: the largest change of one coordinate in one quasi-Newton step (z: log-scales for the noise, so
#: a factor e² at most)
QN_MAX_STEP = 2.0
#: step lengths tried by the line search (1, ¼, …) before an EM update is taken instead
QN_BACKTRACKS = 5
#: the longest step (in units of the quasi-Newton direction) the line search expands to
QN_EXPAND = 8.0


def bfgs_update(Hinv: np.ndarray, s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Powell-damped BFGS update of the inverse curvature for the step s and gradient change y.

    Where the objective is not concave along s (sᵀy < 0.2 sᵀBs, B = H⁻¹⁻¹), y is blended with Bs
    so that the update stays positive definite and still takes in what the step showed.
    """
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(y))) or not np.any(s):
        return Hinv
    B = np.linalg.inv(Hinv)
    Bs = B @ s
    sBs = float(s @ Bs)
    sy = float(s @ y)
    if sBs <= 0:
        return Hinv
    if sy < 0.2 * sBs:
        phi = 0.8 * sBs / (sBs - sy)
        y = phi * y + (1.0 - phi) * Bs
        sy = float(s @ y)
    rho = 1.0 / sy
    left = np.eye(len(s)) - rho * np.outer(s, y)
    return left @ Hinv @ left.T + rho * np.outer(s, s)


@jit
def q_derivatives(problem: FitProblem, theta: Theta, e: GaussianPosterior, *, hessian: bool):
    """(value, gradient[, Hessian]) in θ of −Q(θ | q) − log p(θ) with q = ``e`` (cubature)."""
    points, pairs = cubature_points(e.states, e.covariances, e.cross)
    mp = ExpectedLearningProblem(
        problem=problem,
        points=points,
        pairs=pairs,
        weights=jnp.where(e.status == RESULTS.nonfinite, 0.0, 1.0).astype(e.states.dtype),
        theta_ref=theta,
        rho_theta=jnp.zeros((), theta.dtype),
    )
    value, grad = jax.value_and_grad(mp.value)(theta)
    if not hessian:
        return value, grad, None
    return value, grad, jax.hessian(mp.value)(theta)


def qn_start(problem: FitProblem, theta: Theta, e: GaussianPosterior):
    """(H⁻¹, g) in z at θ: the inverse curvature and the ascent gradient.

    The curvature is the complete-data information −∇²Q (EM's metric), its eigenvalues clipped
    to be positive. Where Q's derivatives are not finite (an E-step that failed: a noise scale
    that collapsed, a posterior not finite) there is no curvature to start from: the identity
    and a zero gradient, so the next epoch takes a plain EM update (its line search has no
    ascent direction) and starts the curvature again after it.
    """
    coords = Coordinates(problem, theta)
    _, grad, hess = q_derivatives(problem, theta, e, hessian=True)
    grad, hess = np.asarray(grad, float), np.asarray(hess, float)
    scale = coords.dtheta_dz(theta)
    Hz = scale[:, None] * hess * scale[None, :] + np.diag(np.where(coords.mask, grad * scale, 0.0))
    if not (np.all(np.isfinite(Hz)) and np.all(np.isfinite(grad))):
        P = theta.shape[0]
        return jnp.eye(P, dtype=theta.dtype), jnp.zeros((P,), theta.dtype)
    w, U = np.linalg.eigh(0.5 * (Hz + Hz.T))
    top = float(np.max(np.abs(w))) if w.size else 1.0
    w = np.maximum(w, 1e-10 * max(top, 1e-300))
    Hinv = (U / w) @ U.T
    g = coords.ascent(grad, theta)
    return jnp.asarray(Hinv, theta.dtype), jnp.asarray(g, theta.dtype)


def qn_gradient(problem: FitProblem, theta: Theta, e: GaussianPosterior):
    """The ascent gradient g in z at θ (of the log-evidence + log-prior; Fisher's identity)."""
    grad = q_derivatives(problem, theta, e, hessian=False)[1]
    return jnp.asarray(Coordinates(problem, theta).ascent(grad, theta), theta.dtype)


def log_prior_value(problem: FitProblem, theta: Theta) -> float:
    """The log-prior log p(θ) (0 without a prior)."""
    return 0.0 if problem.log_prior is None else -float(problem.neg_log_prior(theta))


class Coordinates:
    """θ ⇄ z for the quasi-Newton steps: log for learned noise ``scale_parameters``, else θ."""

    def __init__(self, problem: FitProblem, theta: Theta):
        marks = jtu.tree_map(lambda x: np.zeros(np.shape(x)), problem.template)
        for field in ("process_noise", "obs_noise"):
            noise = getattr(problem.template, field, None)
            scale = None if noise is None else noise.scale_parameters()
            if problem.trains(field) and scale is not None:
                ones = np.ones(np.shape(scale))
                marks = eqx.tree_at(
                    lambda s, f=field: getattr(s, f).scale_parameters(), marks, replace=ones
                )
        flat = [np.ravel(a) for a in jtu.tree_leaves(marks)]
        self.mask = (np.concatenate(flat) > 0.5) if flat else np.zeros(0, bool)
        self.dtype = theta.dtype

    def z(self, theta) -> np.ndarray:
        """The coordinates z of θ."""
        t = np.asarray(theta, float)
        return np.where(self.mask, np.log(np.abs(np.where(self.mask, t, 1.0))), t)

    def theta(self, z: np.ndarray) -> Theta:
        """θ of z, in θ's dtype."""
        return jnp.asarray(np.where(self.mask, np.exp(np.where(self.mask, z, 0.0)), z), self.dtype)

    def dtheta_dz(self, theta) -> np.ndarray:
        """The diagonal Jacobian dθ/dz at θ."""
        return np.where(self.mask, np.asarray(theta, float), 1.0)

    def ascent(self, grad, theta) -> np.ndarray:
        """The ascent gradient of F = ℓ + log p in z from ∇θ of −Q − log p."""
        return -np.asarray(grad, float) * self.dtheta_dz(theta)
