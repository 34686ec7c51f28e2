"""Noise models: the densities p_w and p_v of Eq. 1 that weight the residuals of Eq. 9.

Every noise model gives, for a residual r ∈ R^d and a boolean mask of the dimensions that are
present:

- ``nll(r, mask)``: −log p(r_obs), the negative log-density of the present components (their
  marginal), normaliser included;
- ``sqrt_curvature(r, mask)``: a d × d matrix S with W = SᵀS a positive semi-definite curvature of
  ``nll`` at r, and, for Gaussian models, SᵀS r = ∇nll. Second-order solvers build Gauss–Newton
  blocks JᵀWJ from it: for Gaussian noise S r is the whitened residual; for Student-t noise S is the
  iteratively-reweighted (Fisher-scoring) weight, always positive definite.

Masked components contribute nothing: for a full covariance the present components keep their
exact marginal (the covariance is reduced to the present rows and columns).
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from ceemx.lib.dense import eigh, masked_cholesky, solve_triangular, symmetrize, whitening_matrix
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import Scalar

__all__ = [
    "AbstractNoise",
    "AbstractGaussianNoise",
    "DiagonalGaussian",
    "CholeskyGaussian",
    "StudentT",
    "as_noise",
]

_LOG_2PI = math.log(2.0 * math.pi)


@jax.jit  # one program per shape (op by op: a transfer, the factorisation and tril compiled)
def _cholesky_tril(cov: Array) -> Array:
    return jnp.tril(jnp.linalg.cholesky(cov))


def _full_mask(r: Float[Array, " d"], mask: Bool[Array, " d"] | None) -> Bool[Array, " d"]:
    if mask is None:
        return jnp.ones(r.shape, dtype=bool)
    return jnp.broadcast_to(mask, r.shape)


class AbstractNoise(eqx.Module):
    """A noise density on R^d (generic log-density interface).

    Subclasses implement :meth:`log_prob`. The default :meth:`sqrt_curvature` is the Hessian of the
    negative log-density projected onto the positive semi-definite cone (eigenvalues clipped at
    zero), which makes any smooth density usable by the second-order smoother.
    """

    @abc.abstractmethod
    def log_prob(self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None) -> Scalar:
        """Log-density of the present components of the residual ``r``."""

    def nll(self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None) -> Scalar:
        """Negative log-density, −log p(r_present)."""
        return -self.log_prob(r, mask)

    #: Whether :meth:`sqrt_curvature` is a diagonal matrix for every residual; then
    #: :meth:`sqrt_curvature_diagonal` gives its diagonal and the linearisation scales rows
    #: instead of multiplying by a d × d matrix per step (O(d²) instead of O(d³) work).
    diagonal_curvature: ClassVar[bool] = False

    def sqrt_curvature_diagonal(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, " d"]:
        """The diagonal of :meth:`sqrt_curvature` (only where ``diagonal_curvature``)."""
        return jnp.diagonal(self.sqrt_curvature(r, mask))

    def sqrt_curvature(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, "d d"]:
        """A matrix S with SᵀS a positive semi-definite curvature of ``nll`` at ``r``."""
        hess = jax.hessian(lambda z: self.nll(z, mask))(r)
        hess = symmetrize(hess)
        w, v = eigh(hess)  # Jacobi, not LAPACK: batched over time steps (ceemx.lib.dense)
        return jnp.sqrt(jnp.clip(w, 0.0))[:, None] * v.T

    @property
    def is_gaussian(self) -> bool:
        """Whether ``nll`` is exactly ½‖S r‖² plus a constant (Gauss–Newton applies exactly)."""
        return False

    def sample(self, key: PRNGKeyArray, shape: tuple[int, ...], dtype) -> Float[Array, ...]:
        """Draws with leading axes ``shape`` and the residual dimension last.

        Raises:
            TypeError: for a density without a sampler (simulation and bootstrap particle
                filtering need one; subclass and implement ``sample``).
        """
        raise TypeError(
            f"{type(self).__name__} has no sampler: implement `sample(key, shape, dtype)` to "
            "simulate it or to use it in a particle filter."
        )

    def check(self, name: str) -> None:
        """Raise ``ValueError`` naming ``name`` when the parameters are invalid (host-side)."""


class AbstractGaussianNoise(AbstractNoise):
    """Zero-mean Gaussian noise N(0, Σ) with Σ = L Lᵀ."""

    @abc.abstractmethod
    def cholesky(self) -> Float[Array, "d d"]:
        """Lower Cholesky factor L of the covariance Σ."""

    @property
    def is_gaussian(self) -> bool:
        """Gaussian noise models are exactly quadratic in the residual."""
        return True

    def sqrt_curvature(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, "d d"]:
        """The whitening matrix L⁻¹ of the present components (zero rows for masked ones)."""
        return whitening_matrix(self.cholesky().astype(r.dtype), _full_mask(r, mask))

    def covariance(self) -> Float[Array, "d d"]:
        """Σ = L Lᵀ."""
        L = self.cholesky()
        return L @ L.T

    def sample(self, key: PRNGKeyArray, shape: tuple[int, ...], dtype) -> Float[Array, ...]:
        """L z with z standard normal, leading axes ``shape``."""
        L = self.cholesky().astype(dtype)
        return jax.random.normal(key, (*shape, L.shape[0]), dtype) @ L.T

    def whiten(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, " d"]:
        """Whitened residual L⁻¹ r of the present components (zero where masked)."""
        return self.sqrt_curvature(r, mask) @ r

    def log_prob(self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None) -> Scalar:
        """Exact Gaussian log-density of the present components."""
        mask = _full_mask(r, mask)
        chol = masked_cholesky(self.cholesky().astype(r.dtype), mask)
        z = solve_triangular(chol, jnp.where(mask, r, 0.0))
        k = jnp.sum(mask).astype(r.dtype)
        return -0.5 * jnp.sum(z**2) - jnp.sum(jnp.log(jnp.abs(jnp.diag(chol)))) - 0.5 * k * _LOG_2PI


class DiagonalGaussian(AbstractGaussianNoise):
    """N(0, diag(scale²)); ``scale`` is a scalar or a length-d vector of standard deviations."""

    scale: Float[Array, ...]
    dim: int = eqx.field(static=True)

    def __init__(self, scale, dim: int):
        self.scale = jnp.asarray(scale)
        self.dim = int(dim)

    def std(self) -> Float[Array, " d"]:
        """Standard deviations as a length-d vector."""
        return jnp.broadcast_to(self.scale, (self.dim,))

    def cholesky(self) -> Float[Array, "d d"]:
        """diag(scale)."""
        return jnp.diag(self.std())

    # Diagonal fast paths (no d×d Cholesky per step).
    diagonal_curvature: ClassVar[bool] = True

    def sqrt_curvature_diagonal(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, " d"]:
        """The diagonal of diag(mask / scale): 1/scale on present components, 0 on masked ones."""
        mask = _full_mask(r, mask)
        return jnp.where(mask, 1.0 / self.std().astype(r.dtype), 0.0)

    def sqrt_curvature(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, "d d"]:
        """diag(mask / scale)."""
        return jnp.diag(self.sqrt_curvature_diagonal(r, mask))

    def log_prob(self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None) -> Scalar:
        """Sum of independent normal log-densities over the present components."""
        mask = _full_mask(r, mask)
        s = self.std().astype(r.dtype)
        terms = -0.5 * (r / s) ** 2 - jnp.log(s) - 0.5 * _LOG_2PI
        return jnp.sum(jnp.where(mask, terms, 0.0))

    def check(self, name: str) -> None:
        """Scales must be finite and positive."""
        _check_positive(name + ".scale", self.scale)


class CholeskyGaussian(AbstractGaussianNoise):
    """N(0, L Lᵀ) with a full lower-triangular Cholesky factor ``chol`` (positive diagonal)."""

    chol: Float[Array, "d d"]

    def __init__(self, chol=None, *, cov=None):
        if (chol is None) == (cov is None):
            raise ValueError("CholeskyGaussian: give exactly one of `chol` or `cov`.")
        if cov is not None:
            self.chol = _cholesky_tril(cov if isinstance(cov, jax.Array) else np.asarray(cov))
        elif chol is None or isinstance(chol, jax.Array) or np.ndim(chol) < 2:  # traced, on device
            self.chol = jnp.tril(jnp.asarray(chol))
        else:  # host data: NumPy's tril and a transfer (JAX's compiled a program per shape)
            self.chol = as_jax(np.tril(np.asarray(chol)))

    def cholesky(self) -> Float[Array, "d d"]:
        """The stored factor."""
        return self.chol

    def check(self, name: str) -> None:
        """The factor must be square with a finite, positive diagonal."""
        import numpy as np

        c = np.asarray(self.chol)
        if c.ndim != 2 or c.shape[0] != c.shape[1]:
            raise ValueError(f"`{name}.chol` must be a square matrix, got shape {c.shape}.")
        _check_positive(name + ".chol diagonal", np.diag(c))


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
        mask = _full_mask(r, mask)
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
        mask = _full_mask(r, mask)
        z, chol = self._whitened(r, mask)
        k = jnp.sum(mask).astype(r.dtype)
        nu = self.df.astype(r.dtype)
        w = (nu + k) / (nu + jnp.sum(z**2))
        return jnp.sqrt(w) * whitening_matrix(self._chol(r.dtype), mask)

    def check(self, name: str) -> None:
        """Scale and degrees of freedom must be positive."""
        import numpy as np

        s = np.asarray(self.scale)
        _check_positive(name + ".scale", np.diag(s) if s.ndim == 2 else s)
        _check_positive(name + ".df", self.df)


def as_noise(value: AbstractNoise | ArrayLike, dim: int) -> AbstractNoise:
    """A noise model as given, or ``DiagonalGaussian(value, dim)`` for a scale (scalar, vector)."""
    return value if isinstance(value, AbstractNoise) else DiagonalGaussian(value, dim)


def _check_positive(name: str, value) -> None:
    import numpy as np

    v = np.asarray(value)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite; got {v}.")
    if np.any(v <= 0):
        idx = int(np.argmax(np.ravel(v) <= 0))
        raise ValueError(f"`{name}` must be positive; entry {idx} is {np.ravel(v)[idx]}.")
