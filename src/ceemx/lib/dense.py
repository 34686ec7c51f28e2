"""Small dense linear algebra shared by the solvers: SPD solves with a failure flag, whitening.

Everything here is pure JAX (jit/vmap-safe) and knows nothing of EM.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular
from jaxtyping import Array, Bool, Float

__all__ = [
    "cholesky_solve",
    "masked_cholesky",
    "symmetrize",
    "whiten",
    "whitening_matrix",
]


def symmetrize(a: Float[Array, "... k k"]) -> Float[Array, "... k k"]:
    """½(A + Aᵀ) over the last two axes."""
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


def cholesky_solve(
    a: Float[Array, "k k"], b: Float[Array, " k"]
) -> tuple[Float[Array, " k"], Bool[Array, ""]]:
    """Solve the symmetric positive-definite system A x = b by Cholesky; flag failure.

    A is symmetrised first. ``ok`` is False when the factor is not finite or has a pivot at
    rounding-noise level (A numerically singular or indefinite); ``x`` is then zeros.
    """
    a = symmetrize(a)
    chol = jnp.linalg.cholesky(a)
    k = a.shape[-1]
    pivots = jnp.diagonal(chol)
    floor = k * jnp.finfo(a.dtype).eps * jnp.max(jnp.abs(jnp.diagonal(a)))
    ok = jnp.all(jnp.isfinite(chol)) & jnp.all(pivots**2 > floor)
    x = jax.scipy.linalg.cho_solve((chol, True), b)
    ok = ok & jnp.all(jnp.isfinite(x))
    return jnp.where(ok, x, 0.0), ok


def masked_cholesky(chol: Float[Array, "d d"], mask: Bool[Array, " d"]) -> Float[Array, "d d"]:
    """Cholesky factor of Σ = L Lᵀ restricted to the present rows/columns, identity elsewhere.

    With M = diag(mask), Σ' = M Σ M + (I − M) is, after a permutation, block-diagonal with the
    present block Σ_oo and an identity block, so whitening by chol(Σ') gives the exact marginal
    density of the present components while masked components (residual set to zero) add nothing.
    """
    m = mask.astype(chol.dtype)
    cov = chol @ chol.T
    cov = cov * m[:, None] * m[None, :] + jnp.diag(1.0 - m)
    return jnp.linalg.cholesky(cov)


def whiten(
    chol: Float[Array, "d d"], mask: Bool[Array, " d"], r: Float[Array, " d"]
) -> Float[Array, " d"]:
    """L_o⁻¹ r_o of the present components (zeros where masked), L_o = :func:`masked_cholesky`."""
    return solve_triangular(masked_cholesky(chol, mask), jnp.where(mask, r, 0.0), lower=True)


def whitening_matrix(chol: Float[Array, "d d"], mask: Bool[Array, " d"]) -> Float[Array, "d d"]:
    """The matrix S with S r = :func:`whiten` (chol, mask, r): L_o⁻¹ with masked rows zeroed."""
    eye = jnp.eye(chol.shape[-1], dtype=chol.dtype)
    s = solve_triangular(masked_cholesky(chol, mask), eye, lower=True)
    return s * mask[:, None].astype(chol.dtype)
