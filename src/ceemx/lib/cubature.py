"""Gaussian cubature: expectations E[h(z)], z ~ N(μ, Σ), by a third-degree spherical–radial rule.

The rule (Arasaratnam & Haykin 2009; the unscented transform with κ = 0) puts 2d equally weighted
points at μ ± √d · s_i, where s_i are the columns of a square root of Σ. It is exact for every
polynomial h of degree ≤ 3 — so for the first and second moments of an affine map, which makes
expectations of quadratic forms of linear-Gaussian residuals exact — and costs 2d evaluations of h.

The square root is the lower Cholesky factor in its positive-semidefinite form
(:func:`ceemx.lib.dense.cholesky` with ``psd=True``): pivots at rounding level are taken as zero,
so it exists for the singular and rounding-level indefinite pairwise covariances of a nearly
deterministic transition (plain Cholesky fails there), and L Lᵀ = Σ to rounding. Any square root
gives the same rule's moments — every polynomial of degree ≤ 3 is integrated exactly whichever
square root is used; the factor orients the points (the classic cubature Kalman filter's choice).
It is elementwise JAX, not LAPACK: for the (T, 2n, 2n) pair blocks of a long record it is about
100× faster than LAPACK's batched eigh, and batched LAPACK calls that may run concurrently
deadlock jaxlib 0.10.2 on small machines (docs/known_issues.md).
:func:`sqrtm_psd`, the symmetric root, is kept for callers who want that orientation.

Pure JAX, jit/vmap-safe; knows nothing of EM.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ceemx.lib.dense import cholesky, eigh

__all__ = [
    "pair_covariances",
    "pair_points_first_half",
    "psd_sqrt",
    "sigma_points",
    "sqrtm_psd",
]


def psd_sqrt(cov: Float[Array, "... d d"]) -> Float[Array, "... d d"]:
    """A square root L (L Lᵀ = Σ, lower-triangular) of positive semi-definite matrices; batched."""
    return cholesky(cov, psd=True)


def sqrtm_psd(cov: Float[Array, "... d d"]) -> Float[Array, "... d d"]:
    """Symmetric square root of a (numerically) positive semi-definite matrix (eigenvalues ≥ 0).

    Jacobi eigendecomposition (:func:`ceemx.lib.dense.eigh`, no LAPACK), negative eigenvalues
    clipped at zero.
    """
    w, v = eigh(cov)
    return (v * jnp.sqrt(jnp.clip(w, 0.0))[..., None, :]) @ jnp.swapaxes(v, -1, -2)


def sigma_points(
    mean: Float[Array, "... d"], cov: Float[Array, "... d d"]
) -> Float[Array, "... K d"]:
    """The 2d points μ ± √d s_i of the third-degree rule (each of weight 1/(2d)); batched.

    s_i are the columns of :func:`psd_sqrt` (Σ): singular covariances are fine.
    """
    d = mean.shape[-1]
    root = jnp.sqrt(jnp.asarray(d, mean.dtype)) * psd_sqrt(cov)
    offsets = jnp.swapaxes(root, -1, -2)  # rows are the scaled columns s_i
    return jnp.concatenate([mean[..., None, :] + offsets, mean[..., None, :] - offsets], axis=-2)


def pair_covariances(
    cov: Float[Array, "T n n"], cross: Float[Array, "T-1 n n"]
) -> Float[Array, "T-1 n2 n2"]:
    """Covariances of the pairs (z_t, z_{t+1}) from marginal blocks and Cov(z_{t+1}, z_t) blocks."""
    upper = jnp.concatenate([cov[:-1], jnp.swapaxes(cross, -1, -2)], axis=-1)
    lower = jnp.concatenate([cross, cov[1:]], axis=-1)
    return jnp.concatenate([upper, lower], axis=-2)


def pair_points_first_half(pairs: Float[Array, "S K2 d2"], n: int):
    """The distinct first halves x of the points of pairs (x, x'), and a map back to the points.

    :func:`sigma_points` of a pair's Gaussian (d = 2n) lays out (μ + s_i) for i < 2n, then
    (μ − s_i), s_i the scaled columns of the lower-triangular root: the columns i ≥ n are zero in
    their first n entries, so those 2n points keep x exactly at its mean, and of the 4n points
    only 2n + 1 differ in x — a function of x alone (the dynamics of a transition) need be
    evaluated only there. Returns (S, D, n) those x (columns 0…n−1 with +, with −, then the
    mean; D = 2n + 1) and ``spread``: values at them (S, D, …) → (S, 4n, …), one per point, by
    static slices (a gather's reverse mode, a scatter-add, costs more than what it saves).
    Points laid out otherwise (K₂ ≠ 4n): each is its own (D = K₂, ``spread`` the identity).
    """
    K2 = pairs.shape[1]
    if K2 != 4 * n:
        return pairs[..., :n], lambda values: values
    first = jnp.concatenate(
        [pairs[:, :n, :n], pairs[:, 2 * n : 3 * n, :n], pairs[:, n : n + 1, :n]], axis=1
    )

    def spread(values):
        mean = jnp.broadcast_to(values[:, 2 * n :], (values.shape[0], n) + values.shape[2:])
        return jnp.concatenate([values[:, :n], mean, values[:, n : 2 * n], mean], axis=1)

    return first, spread
