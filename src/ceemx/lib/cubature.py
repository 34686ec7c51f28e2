"""Gaussian cubature: expectations E[h(z)], z ~ N(μ, Σ), by a third-degree spherical–radial rule.

The rule (Arasaratnam & Haykin 2009; the unscented transform with κ = 0) puts 2d equally weighted
points at μ ± √d · s_i, where s_i are the columns of a square root of Σ. It is exact for every
polynomial h of degree ≤ 3 — so for the first and second moments of an affine map, which makes
expectations of quadratic forms of linear-Gaussian residuals exact — and costs 2d evaluations of h.

The square root is the symmetric one from an eigendecomposition with negative eigenvalues clipped
at zero: it exists for singular and rounding-level indefinite covariances (Cholesky would fail on
the near-singular pairwise covariances of a nearly deterministic transition). Any square root gives
the same rule's moments.

Pure JAX, jit/vmap-safe; knows nothing of EM.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ceemx.lib.dense import symmetrize

__all__ = ["pair_covariances", "sigma_points", "sqrtm_psd"]


def sqrtm_psd(cov: Float[Array, "... d d"]) -> Float[Array, "... d d"]:
    """Symmetric square root of a (numerically) positive semi-definite matrix (eigenvalues ≥ 0)."""
    w, v = jnp.linalg.eigh(symmetrize(cov))
    return (v * jnp.sqrt(jnp.clip(w, 0.0))[..., None, :]) @ jnp.swapaxes(v, -1, -2)


def sigma_points(
    mean: Float[Array, "... d"], cov: Float[Array, "... d d"]
) -> Float[Array, "... K d"]:
    """The 2d points μ ± √d s_i of the third-degree rule (each of weight 1/(2d)); batched."""
    d = mean.shape[-1]
    root = jnp.sqrt(jnp.asarray(d, mean.dtype)) * sqrtm_psd(cov)
    offsets = jnp.swapaxes(root, -1, -2)  # rows are the scaled columns s_i
    return jnp.concatenate([mean[..., None, :] + offsets, mean[..., None, :] - offsets], axis=-2)


def pair_covariances(
    cov: Float[Array, "T n n"], cross: Float[Array, "T-1 n n"]
) -> Float[Array, "T-1 n2 n2"]:
    """Covariances of the pairs (z_t, z_{t+1}) from marginal blocks and Cov(z_{t+1}, z_t) blocks."""
    upper = jnp.concatenate([cov[:-1], jnp.swapaxes(cross, -1, -2)], axis=-1)
    lower = jnp.concatenate([cross, cov[1:]], axis=-1)
    return jnp.concatenate([upper, lower], axis=-2)
