"""Multivariate Student-t noise: heavy tails for observations with outliers."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ceemx.lib.dense import masked_cholesky, solve_triangular, whitening_matrix
from ceemx.lib.typing import Scalar
from ceemx.models.noise import AbstractNoise, check_positive, check_scale_shape, full_mask

__all__ = ["StudentT"]


class StudentT(AbstractNoise):
    """Multivariate Student-t noise with ``df`` degrees of freedom and scale matrix L Lᵀ.

    log p(r) = log Γ((ν+k)/2) − log Γ(ν/2) − (k/2) log(νπ) − log|L| − ((ν+k)/2) log(1 + δ²/ν),
    δ² = ‖L⁻¹r‖², k the number of present components. The curvature used by the smoother is the
    Fisher-scoring / IRLS weight ((ν+k)/(ν+δ²)) L⁻ᵀL⁻¹ — positive definite everywhere, and with
    SᵀS r = ∇nll(r) — so each Gauss–Newton step is a majorise–minimise step.
    """

    scale: Float[Array, ...]
    df: Float[Array, ""]
    dim: int = eqx.field(static=True)

    def __init__(self, scale, df, dim: int):
        self.scale = jnp.asarray(scale)
        self.df = jnp.asarray(df)
        self.dim = int(dim)

    def _chol(self, dtype) -> Float[Array, "d d"]:
        s = jnp.asarray(self.scale, dtype)
        if s.ndim == 2:
            return jnp.tril(s)
        return jnp.diag(jnp.broadcast_to(s, (self.dim,)))

    def _whitened(self, r, mask):
        chol = masked_cholesky(self._chol(r.dtype), mask)
        z = solve_triangular(chol, jnp.where(mask, r, 0.0))
        return z, chol

    def log_prob(self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None) -> Scalar:
        """Multivariate-t log-density of the present components."""
        mask = full_mask(r, mask)
        z, chol = self._whitened(r, mask)
        k = jnp.sum(mask).astype(r.dtype)
        nu = self.df.astype(r.dtype)
        d2 = jnp.sum(z**2)
        return (
            jax.scipy.special.gammaln(0.5 * (nu + k))
            - jax.scipy.special.gammaln(0.5 * nu)
            - 0.5 * k * jnp.log(nu * jnp.pi)
            - jnp.sum(jnp.log(jnp.abs(jnp.diag(chol))))
            - 0.5 * (nu + k) * jnp.log1p(d2 / nu)
        )

    def sample(self, key: PRNGKeyArray, shape: tuple[int, ...], dtype) -> Float[Array, ...]:
        """A Gaussian scale mixture: L z / sqrt(g), g ~ Gamma(ν/2, rate ν/2)."""
        k1, k2 = jax.random.split(key)
        L = self._chol(dtype)
        z = jax.random.normal(k1, (*shape, L.shape[0]), dtype) @ L.T
        nu = self.df.astype(dtype)
        g = jax.random.gamma(k2, 0.5 * nu, shape, dtype) / (0.5 * nu)
        return z / jnp.sqrt(g)[..., None]

    def sqrt_curvature(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, "d d"]:
        """sqrt((ν+k)/(ν+δ²)) L⁻¹ on the present components."""
        mask = full_mask(r, mask)
        z, chol = self._whitened(r, mask)
        k = jnp.sum(mask).astype(r.dtype)
        nu = self.df.astype(r.dtype)
        w = (nu + k) / (nu + jnp.sum(z**2))
        return jnp.sqrt(w) * whitening_matrix(self._chol(r.dtype), mask)

    def check(self, name: str) -> None:
        """Scale and degrees of freedom must be positive."""
        s = np.asarray(self.scale)
        check_positive(name + ".scale", np.diag(s) if s.ndim == 2 else s)
        check_positive(name + ".df", self.df)

    def check_dimension(self, name: str, dim: int, what: str) -> None:
        """``dim`` equal to the system's, ``scale`` a scalar or of shape (dim,) or (dim, dim)."""
        super().check_dimension(name, dim, what)
        check_scale_shape(name, self.scale, dim, matrix=True)

    def describe(self) -> dict[str, Any]:
        """The scale and the degrees of freedom."""
        return {"scale": self.scale, "df": self.df}
