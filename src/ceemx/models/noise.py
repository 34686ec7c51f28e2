"""Noise models: the densities p_w and p_v of Eq. 1 that weight the residuals of Eq. 9.

Every noise model gives, for a residual r ∈ R^d and a boolean mask of the dimensions that are
present:

- ``nll(r, mask)``: −log p(r_obs), the negative log-density of the present components (their
  marginal), normaliser included;
- ``sqrt_curvature(r, mask)``: a d × d matrix S with W = SᵀS a positive semi-definite curvature of
  ``nll`` at r, and, for Gaussian models, SᵀS r = ∇nll. Second-order solvers build Gauss–Newton
  blocks JᵀWJ from it: for Gaussian noise S r is the whitened residual; for Student-t noise
  (:mod:`ceemx.models.student_t`) S is the iteratively-reweighted (Fisher-scoring) weight, always
  positive definite.

Masked components contribute nothing: for a full covariance the present components keep their
exact marginal (the covariance is reduced to the present rows and columns).

Everything else the library asks of a noise model is a method or class-level flag of
:class:`AbstractNoise`, so a new model is one subclass: ``check_dimension`` (the system's
construction checks), ``describe`` (the fit summary), ``variance_ratios``, ``full_covariance`` and
``masked_fill`` (the residual diagnostics and the noise estimate), ``learnable_in_closed_form``,
``covariance_update`` and ``scaled`` (Laplace EM's closed-form noise M-step and the evidence search
of :func:`ceemx.identification.analysis.noise_estimate.estimate_noise`), ``scale_parameters`` (the
log-coordinates and standard errors of learned standard deviations). Defaults work for any density
where the answer does not depend on the model (a Gaussian from its Cholesky factor alone) and
refuse, naming the class and what to implement, where it does. This file holds the interface and
the Gaussian models; every other model is one class in a file of its own, built with the helpers
at the end of this one (``full_mask``, ``check_positive``, ``check_scale_shape``).
"""

from __future__ import annotations

import abc
import math
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from ceemx.lib.dense import (
    cho_solve,
    cholesky,
    eigh,
    masked_cholesky,
    solve_triangular,
    symmetrize,
    whitening_matrix,
)
from ceemx.lib.tree import as_jax, value_repr
from ceemx.lib.typing import Scalar

__all__ = [
    "SecondMoments",
    "AbstractNoise",
    "AbstractGaussianNoise",
    "DiagonalGaussian",
    "CholeskyGaussian",
    "as_noise",
]

_LOG_2PI = math.log(2.0 * math.pi)


@jax.jit  # one program per shape (op by op: a transfer, the factorisation and tril compiled)
def _cholesky_tril(cov: Array) -> Array:
    return jnp.tril(jnp.linalg.cholesky(cov))


def full_mask(r: Float[Array, " d"], mask: Bool[Array, " d"] | None) -> Bool[Array, " d"]:
    """The present components of ``r`` as a boolean vector (all of them for ``mask=None``)."""
    if mask is None:
        return jnp.ones(r.shape, dtype=bool)
    return jnp.broadcast_to(mask, r.shape)


class SecondMoments(NamedTuple):
    """Mean residual second moments of one noise model: the statistics of its Gaussian M-step.

    Attributes:
        full: (d, d) the mean E[r rᵀ], missing components filled in
            (:meth:`AbstractNoise.masked_fill`).
        diagonal: (d,) the mean E[r_i²] over the samples where component i is present.
        pooled: () the mean E[r_i²] over every present component of every sample.
        present: (d,) whether component i is present in any sample (``None``: always present).
    """

    full: Float[Array, "d d"]
    diagonal: Float[Array, " d"]
    pooled: Scalar
    present: Bool[Array, " d"] | None = None


class AbstractNoise(eqx.Module):
    """A noise density on R^d (generic log-density interface).

    Subclasses implement :meth:`log_prob`. The default :meth:`sqrt_curvature` is the Hessian of the
    negative log-density projected onto the positive semi-definite cone (eigenvalues clipped at
    zero), which makes any smooth density usable by the second-order smoother.
    """

    def __repr__(self) -> str:
        """Equinox's form, with the values of small arrays (``scale=0.05``, not ``f64[]``)."""
        return value_repr(self)

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

    def check_dimension(self, name: str, dim: int, what: str) -> None:
        """Raise ``ValueError`` unless the model is built for residuals of dimension ``dim``.

        Runs when a system is constructed (shapes only, so also under tracing); ``what`` names
        the system's dimension in the message (``"state_dim"``, ``"obs_dim"``). The default reads
        an integer ``dim`` field when the model has one.
        """
        d = getattr(self, "dim", None)
        if isinstance(d, int) and d != dim:
            raise ValueError(f"`{name}` has dimension {d} but the system's {what} is {dim}.")

    def describe(self) -> dict[str, Any]:
        """The named values that show the model in a fit summary (e.g. ``{"std": scale}``)."""
        return {}

    #: Whether the components of a residual are coupled, so that its second moments are taken in
    #: full, a missing component filled in from the present ones (:meth:`masked_fill`), rather
    #: than one component at a time over the samples where it is present.
    full_covariance: ClassVar[bool] = False

    def masked_fill(
        self, second_moment: Float[Array, "d d"], mask: Bool[Array, " d"]
    ) -> Float[Array, "d d"]:
        """E[r rᵀ] of a residual whose present part has second moment ``second_moment``.

        Where :attr:`full_covariance`, the missing part is filled in from its conditional given
        the present part (the complete-data moment of EM for missing observations); otherwise
        ``second_moment`` as given.
        """
        return second_moment

    def variance_ratios(self, second_moment: np.ndarray) -> np.ndarray:
        """diag(L⁻¹ S L⁻ᵀ): the realised second moment S over the model's covariance L Lᵀ.

        Per (whitened) component, on the host; ≈ 1 where the model is consistent with the
        residuals. NaN for a model without a covariance (the default).
        """
        return np.full(np.shape(second_moment)[0], np.nan)

    #: Whether :meth:`covariance_update` and :meth:`scaled` are implemented: Laplace EM learns
    #: the model in closed form and the noise estimate searches its scale.
    learnable_in_closed_form: ClassVar[bool] = False

    def covariance_update(self, moments: SecondMoments) -> AbstractNoise:
        """The model with its covariance set to ``moments`` (the Gaussian M-step).

        Same class and leaf shapes (it replaces the model inside a system being learned).
        """
        raise TypeError(
            f"{type(self).__name__} has no closed-form covariance update: implement "
            "`covariance_update(moments)` and `scaled(c)` and set "
            "`learnable_in_closed_form = True` to learn it with LaplaceEM or estimate_noise."
        )

    def scaled(self, c) -> AbstractNoise:
        """The model with every scale times ``c`` (its covariance times c²); same leaf shapes.

        The default multiplies :meth:`scale_parameters`.
        """
        s = self.scale_parameters()
        if s is None:
            raise TypeError(
                f"{type(self).__name__} cannot be scaled: implement `scaled(c)` or "
                "`scale_parameters()`."
            )
        return self.with_scale_parameters(s * c)

    def scale_parameters(self) -> Any:
        """The leaf of per-component scales that parameterises the model, else ``None``.

        Scales in the sense of a location-scale family (standard deviations for a Gaussian),
        shape () (one scale shared by every component) or (d,). Returned as stored (it locates
        the leaf for ``eqx.tree_at``). Learners take its logarithm as coordinates; the noise
        estimate learns it per component; standard errors of Gaussian scales are σ²/(2N).
        """
        return None

    def with_scale_parameters(self, value) -> AbstractNoise:
        """The model with :meth:`scale_parameters` replaced by ``value``."""
        if self.scale_parameters() is None:
            raise TypeError(f"{type(self).__name__} has no `scale_parameters()` to replace.")
        return eqx.tree_at(lambda noise: noise.scale_parameters(), self, replace=value)


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
        return whitening_matrix(self.cholesky().astype(r.dtype), full_mask(r, mask))

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
        mask = full_mask(r, mask)
        chol = masked_cholesky(self.cholesky().astype(r.dtype), mask)
        z = solve_triangular(chol, jnp.where(mask, r, 0.0))
        k = jnp.sum(mask).astype(r.dtype)
        return -0.5 * jnp.sum(z**2) - jnp.sum(jnp.log(jnp.abs(jnp.diag(chol)))) - 0.5 * k * _LOG_2PI

    def check_dimension(self, name: str, dim: int, what: str) -> None:
        """The ``dim`` field when there is one, then the shape of the Cholesky factor."""
        super().check_dimension(name, dim, what)
        shape = tuple(jax.eval_shape(self.cholesky).shape)
        if shape != (dim, dim):
            raise ValueError(
                f"`{name}` has a covariance of shape {shape} but the system's {what} is {dim}."
            )

    def describe(self) -> dict[str, Any]:
        """The marginal standard deviations sqrt(diag Σ)."""
        chol = np.asarray(self.cholesky(), np.float64)
        return {"marginal std": np.sqrt(np.sum(chol**2, axis=1))}

    #: A Gaussian couples its components unless its covariance is diagonal.
    full_covariance: ClassVar[bool] = True

    def masked_fill(
        self, second_moment: Float[Array, "d d"], mask: Bool[Array, " d"]
    ) -> Float[Array, "d d"]:
        """The missing part filled in from its Gaussian conditional given the present part."""
        if not self.full_covariance:
            return second_moment
        R = self.covariance()
        m = R.shape[-1]
        eye = jnp.eye(m, dtype=R.dtype)
        Mo = jnp.diag(mask.astype(R.dtype))
        # (M R M + I − M)⁻¹ by an elementwise Cholesky: this runs batched over time steps, where
        # batched LAPACK calls can deadlock (ceemx.lib.dense)
        inv_o = Mo @ cho_solve(cholesky(Mo @ R @ Mo + eye - Mo), eye) @ Mo
        K = (eye - Mo) @ R @ inv_o
        IK = eye + K
        cond = (eye - Mo) @ (R - R @ inv_o @ R) @ (eye - Mo)
        return IK @ second_moment @ IK.T + cond

    def variance_ratios(self, second_moment: np.ndarray) -> np.ndarray:
        """diag(L⁻¹ S L⁻ᵀ) by two triangular solves."""
        L = np.asarray(self.cholesky(), float)
        W = np.linalg.solve(L, np.linalg.solve(L, second_moment).T)
        return np.diagonal(W)


class DiagonalGaussian(AbstractGaussianNoise):
    """N(0, diag(scale²)); ``scale`` is a scalar or a length-d vector of standard deviations."""

    scale: Float[Array, ...]
    dim: int = eqx.field(static=True)

    def __init__(self, scale, dim: int):
        self.scale = as_jax(scale)  # a NumPy value transferred, not staged through a program
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
        mask = full_mask(r, mask)
        return jnp.where(mask, 1.0 / self.std().astype(r.dtype), 0.0)

    def sqrt_curvature(
        self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None
    ) -> Float[Array, "d d"]:
        """diag(mask / scale)."""
        return jnp.diag(self.sqrt_curvature_diagonal(r, mask))

    def log_prob(self, r: Float[Array, " d"], mask: Bool[Array, " d"] | None = None) -> Scalar:
        """Sum of independent normal log-densities over the present components."""
        mask = full_mask(r, mask)
        s = self.std().astype(r.dtype)
        terms = -0.5 * (r / s) ** 2 - jnp.log(s) - 0.5 * _LOG_2PI
        return jnp.sum(jnp.where(mask, terms, 0.0))

    def check(self, name: str) -> None:
        """Scales must be finite and positive."""
        check_positive(name + ".scale", self.scale)

    def check_dimension(self, name: str, dim: int, what: str) -> None:
        """``dim`` equal to the system's, ``scale`` a scalar or of shape (dim,)."""
        AbstractNoise.check_dimension(self, name, dim, what)  # the scale, not the factor
        check_scale_shape(name, self.scale, dim)

    def describe(self) -> dict[str, Any]:
        """The standard deviations."""
        return {"std": self.scale}

    full_covariance: ClassVar[bool] = False

    def variance_ratios(self, second_moment: np.ndarray) -> np.ndarray:
        """diag(S) / scale²."""
        var = np.broadcast_to(np.asarray(self.scale, float) ** 2, (self.dim,))
        return np.diagonal(second_moment) / var

    learnable_in_closed_form: ClassVar[bool] = True

    def covariance_update(self, moments: SecondMoments) -> DiagonalGaussian:
        """A scalar scale the pooled std, else one std per component.

        A component never present keeps its scale.
        """
        old = jnp.asarray(self.scale)
        if old.ndim == 0:
            scale = jnp.sqrt(moments.pooled)
        else:
            scale = jnp.sqrt(moments.diagonal)
            if moments.present is not None:
                scale = jnp.where(moments.present, scale, jnp.broadcast_to(old, scale.shape))
        return DiagonalGaussian(scale.astype(old.dtype).reshape(old.shape), self.dim)

    def scale_parameters(self) -> Any:
        """``scale`` (typed ``Any``: ``eqx.tree_at`` calls it on a tree of placeholders)."""
        return self.scale


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
        c = np.asarray(self.chol)
        if c.ndim != 2 or c.shape[0] != c.shape[1]:
            raise ValueError(f"`{name}.chol` must be a square matrix, got shape {c.shape}.")
        check_positive(name + ".chol diagonal", np.diag(c))

    def check_dimension(self, name: str, dim: int, what: str) -> None:
        """``chol`` of shape (dim, dim)."""
        shape = tuple(jnp.shape(self.chol))
        if int(shape[-1]) != dim:
            raise ValueError(
                f"`{name}` has dimension {shape[-1]} but the system's {what} is {dim}."
            )
        if shape != (dim, dim):
            raise ValueError(f"`{name}.chol` must have shape ({dim}, {dim}); got {shape}.")

    learnable_in_closed_form: ClassVar[bool] = True

    def covariance_update(self, moments: SecondMoments) -> CholeskyGaussian:
        """The Cholesky factor of the (symmetrised) full moment."""
        full = moments.full
        return CholeskyGaussian(jnp.linalg.cholesky(0.5 * (full + full.T)).astype(self.chol.dtype))

    def scaled(self, c) -> CholeskyGaussian:
        """``chol`` times ``c``."""
        return CholeskyGaussian(jnp.asarray(self.chol) * c)


def as_noise(value: AbstractNoise | ArrayLike, dim: int) -> AbstractNoise:
    """A noise model as given, or ``DiagonalGaussian(value, dim)`` for a scale (scalar, vector)."""
    return value if isinstance(value, AbstractNoise) else DiagonalGaussian(value, dim)


def check_scale_shape(name: str, scale, dim: int, matrix: bool = False) -> None:
    """Raise ``ValueError`` unless ``scale`` is a scalar, (dim,) or, with ``matrix``, (dim, dim)."""
    shape = tuple(jnp.shape(scale))
    if not (shape in ((), (dim,)) or (matrix and shape == (dim, dim))):
        raise ValueError(
            f"`{name}.scale` must be a scalar or have shape ({dim},); got shape {shape}."
        )


def check_positive(name: str, value) -> None:
    """Raise ``ValueError`` naming ``name`` unless every entry of ``value`` is finite and > 0."""
    v = np.asarray(value)
    if not np.all(np.isfinite(v)):
        raise ValueError(f"`{name}` must be finite; got {v}.")
    if np.any(v <= 0):
        idx = int(np.argmax(np.ravel(v) <= 0))
        raise ValueError(f"`{name}` must be positive; entry {idx} is {np.ravel(v)[idx]}.")
