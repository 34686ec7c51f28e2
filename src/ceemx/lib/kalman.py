"""Linear-Gaussian conditioning: the Kalman update in square-root-friendly form, with masks.

Nothing here knows about systems: a Gaussian x ~ N(μ, P) is observed as y = C x + v,
v ~ N(0, R), with some components of y missing. Used by the fully adapted particle filter (one
update shared by every particle) and by Kalman-type filters.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ceemx.lib.dense import cho_solve, cholesky, masked_cholesky, solve_triangular, symmetrize
from ceemx.lib.typing import Scalar

__all__ = ["GaussianUpdate", "gaussian_update", "predictive_log_density"]

_LOG_2PI = math.log(2.0 * math.pi)


class GaussianUpdate(eqx.Module):
    """The parts of conditioning N(μ, P) on y = C x + v that do not depend on μ or y.

    Attributes:
        C: (m, n) observation matrix with the rows of missing components zeroed.
        chol_S: (m, m) lower Cholesky factor of the innovation covariance S = C P Cᵀ + R over the
            present components (identity on missing ones).
        gain: (n, m) Kalman gain K = P Cᵀ S⁻¹ (zero columns for missing components).
        chol_post: (n, n) lower Cholesky factor of the posterior covariance, Joseph form
            (I − K C) P (I − K C)ᵀ + K R Kᵀ.
        mask: (m,) present components.
    """

    C: Float[Array, "m n"]
    chol_S: Float[Array, "m m"]
    gain: Float[Array, "n m"]
    chol_post: Float[Array, "n n"]
    mask: Bool[Array, " m"]

    def mean(self, mu: Float[Array, " n"], y: Float[Array, " m"]) -> Float[Array, " n"]:
        """Posterior mean μ + K (y − C μ) (y: the observation less its offset d)."""
        return mu + self.gain @ (jnp.where(self.mask, y, 0.0) - self.C @ mu)


def gaussian_update(
    P: Float[Array, "n n"],
    C: Float[Array, "m n"],
    chol_R: Float[Array, "m m"],
    mask: Bool[Array, " m"],
) -> GaussianUpdate:
    """Condition N(·, P) on the present components of y = C x + v, v ~ N(0, L_R L_Rᵀ).

    Missing components drop out exactly (the rows of C are zeroed, the noise covariance is
    reduced to the present block, see :func:`ceemx.lib.dense.masked_cholesky`). A non-positive-
    definite result shows as NaN in the factors; callers flag it.
    """
    Cm = jnp.where(mask[:, None], C, 0.0)
    L_R = masked_cholesky(chol_R, mask)
    R = L_R @ L_R.T
    S = symmetrize(Cm @ P @ Cm.T + R)
    L_S = cholesky(S)  # elementwise, not LAPACK: batched over steps (ceemx.lib.dense)
    PCt = P @ Cm.T
    # K = P Cᵀ S⁻¹ through two triangular solves: Kᵀ = S⁻¹ C P.
    gain = cho_solve(L_S, PCt.T).T
    gain = jnp.where(mask[None, :], gain, 0.0)
    IKC = jnp.eye(P.shape[0], dtype=P.dtype) - gain @ Cm
    post = symmetrize(IKC @ P @ IKC.T + gain @ R @ gain.T)
    return GaussianUpdate(Cm, L_S, gain, cholesky(post), mask)


def predictive_log_density(
    update: GaussianUpdate, mu: Float[Array, " n"], y: Float[Array, " m"]
) -> Scalar:
    """Log N(y_present; (C μ)_present, S_present): the marginal density of the present components.

    ``y`` is the observation less its offset d.
    """
    r = jnp.where(update.mask, y, 0.0) - update.C @ mu
    z = solve_triangular(update.chol_S, r)
    k = jnp.sum(update.mask).astype(mu.dtype)
    # Missing rows of chol_S are the identity: their log-diagonal is 0 and z is 0 there.
    return -0.5 * jnp.sum(z**2) - jnp.sum(jnp.log(jnp.diag(update.chol_S))) - 0.5 * k * _LOG_2PI
