"""K coupled Lorenz attractors (paper §4.1, Eq. 12–13)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, Real

from ceemx.infra.policy import Runs, program
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import State
from ceemx.models.noise import AbstractNoise, as_noise
from ceemx.models.system import AbstractContinuousSystem, GaussianPrior

__all__ = [
    "CoupledLorenz",
    "coupling_mask",
    "initial_states",
    "random_coupling",
    "random_observation_matrix",
]

#: Mean and standard deviation of the paper's initial-state distribution per attractor (x₁, x₂, x₃).
INITIAL_MEAN = (-6.0, -6.0, 24.0)
INITIAL_STD = 2.5
TRUE_PARAMS = (10.0, 28.0, 8.0 / 3.0)


def _as_float(a, name: str, ndim: int = 1) -> Array:
    """``a`` as a floating-point array (integers promoted: they would be untrainable)."""
    if isinstance(a, list | tuple):
        try:
            a = np.asarray(a)
        except ValueError:
            raise ValueError(
                f"`{name}` must be a rectangular array; got a ragged sequence."
            ) from None
    if hasattr(a, "dtype") and not (
        np.issubdtype(a.dtype, np.number) or np.dtype(a.dtype) == np.bool_
    ):
        raise TypeError(f"`{name}` must be a real array; got dtype {a.dtype}.")
    if hasattr(a, "dtype") and np.issubdtype(a.dtype, np.complexfloating):
        raise TypeError(f"`{name}` must be real; got dtype {a.dtype}.")
    if isinstance(a, np.ndarray | np.generic):  # NumPy and one transfer: no program per shape
        h = a if np.issubdtype(a.dtype, np.floating) else a.astype(float)
        return as_jax(np.atleast_1d(h) if ndim == 1 else h)
    out = jnp.asarray(a)  # JAX arrays, and Python numbers (kept weakly typed, as JAX makes them)
    if not jnp.issubdtype(out.dtype, jnp.floating):  # integers and booleans: the default float
        out = out.astype(float)
    return jnp.atleast_1d(out) if ndim == 1 else out


def coupling_mask(K: int, dtype=jnp.float64) -> Float[Array, "n n"]:
    """(3K, 3K) mask that is 0 on each attractor's own 3×3 block (no self-coupling), 1 elsewhere."""
    own = np.kron(np.eye(K), np.ones((3, 3)))  # NumPy: a constant, no program per K on the host
    return jnp.asarray(1.0 - own, dtype)


class CoupledLorenz(AbstractContinuousSystem):
    r"""K Lorenz attractors coupled linearly and observed through a linear map.

    For attractor k with state (x₁ₖ, x₂ₖ, x₃ₖ):

        ẋ₁ₖ = σₖ (x₂ₖ − x₁ₖ),  ẋ₂ₖ = x₁ₖ (ρₖ − x₃ₖ) − x₂ₖ,  ẋ₃ₖ = x₁ₖ x₂ₖ − βₖ x₃ₖ,

    then ẋ ← ẋ + H x with H ∈ R^{3K×3K} whose own-attractor 3×3 blocks are ignored (no
    self-coupling); y = C x + v. Discretised by RK4 with ``dt`` (paper: 0.04; ``integrator=
    "midpoint"`` for the authors' single-Lorenz scripts). K = 1, H = 0 is the
    single Lorenz system. The state is ordered attractor by attractor: x = (x₁₁, x₂₁, x₃₁, x₁₂, …).

    Attributes:
        sigma, rho, beta: (K,) parameters of each attractor.
        H: (3K, 3K) coupling; entries on the own-attractor blocks have no effect.
        C: (m, 3K) observation matrix.
    """

    sigma: Float[Array, " K"]
    rho: Float[Array, " K"]
    beta: Float[Array, " K"]
    H: Float[Array, "n n"]
    C: Float[Array, "m n"]

    def __init__(
        self,
        sigma,
        rho,
        beta,
        C,
        *,
        H=None,
        dt: float = 0.04,
        integrator: str = "rk4",
        process_noise: AbstractNoise | ArrayLike = 0.01,
        obs_noise: AbstractNoise | ArrayLike = 0.01,
        initial_prior: GaussianPrior | None = None,
    ):
        # Integers would silently be untrainable (filters learn inexact arrays): promote them.
        # Lists and tuples become arrays first (jnp.result_type refuses them).
        self.sigma = _as_float(sigma, "sigma")
        self.rho = _as_float(rho, "rho")
        self.beta = _as_float(beta, "beta")
        K = self.sigma.shape[0]
        if self.rho.shape != (K,) or self.beta.shape != (K,):
            raise ValueError(
                f"`sigma`, `rho`, `beta` must have the same length K; got {self.sigma.shape}, "
                f"{self.rho.shape}, {self.beta.shape}."
            )
        n = 3 * K
        self.C = _as_float(C, "C", ndim=2)
        if self.C.ndim != 2 or self.C.shape[1] != n:
            raise ValueError(f"`C` must have shape (m, {n}); got {self.C.shape}.")
        self.H = as_jax(np.zeros((n, n), self.sigma.dtype)) if H is None else _as_float(H, "H", 2)
        if self.H.shape != (n, n):
            raise ValueError(f"`H` must have shape ({n}, {n}); got {self.H.shape}.")
        m = self.C.shape[0]
        self.dt = float(dt)
        self.integrator = integrator  # pyright: ignore[reportAttributeAccessIssue]
        self.process_noise = as_noise(process_noise, n)
        self.obs_noise = as_noise(obs_noise, m)
        self.initial_prior = initial_prior

    @property
    def K(self) -> int:
        """Number of attractors."""
        return self.sigma.shape[0]

    @property
    def state_dim(self) -> int:
        """The state dimension n = 3K."""
        return 3 * self.K

    @property
    def obs_dim(self) -> int:
        """The observation dimension m (rows of C)."""
        return self.C.shape[0]

    def effective_coupling(self) -> Float[Array, "n n"]:
        """H with the own-attractor blocks zeroed."""
        return self.H * coupling_mask(self.K, self.H.dtype)

    def default_state_mean(self) -> State:
        """The paper's initial-state mean, (−6, −6, 24) per attractor (§4.1)."""
        return jnp.tile(jnp.asarray(INITIAL_MEAN, self.sigma.dtype), self.K)

    def vector_field(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """Eq. 12."""
        z = x.reshape(self.K, 3)
        x1, x2, x3 = z[:, 0], z[:, 1], z[:, 2]
        dx = jnp.stack(
            [
                self.sigma * (x2 - x1),
                x1 * (self.rho - x3) - x2,
                x1 * x2 - self.beta * x3,
            ],
            axis=-1,
        ).reshape(-1)
        return dx + self.effective_coupling() @ x

    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """Eq. 13: y = C x."""
        return self.C @ x

    def linear_observation(
        self, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> tuple[Float[Array, "m n"], Float[Array, " m"]]:
        """Y = C x + 0: linear in the state (particle filters adapt fully)."""
        return self.C, jnp.zeros((self.C.shape[0],), self.C.dtype)


def random_coupling(
    key: PRNGKeyArray, K: int, frobenius: float = 5.0, dtype=jnp.float64
) -> Float[Array, "n n"]:
    """Standard-normal H, own-attractor blocks zeroed, scaled to the given Frobenius norm."""
    return _random_coupling(key, K, jnp.asarray(frobenius, dtype), dtype)


@program(runs=Runs.ONCE)
def _random_coupling(key, K: int, frobenius, dtype):
    # One program per (K, dtype), run once: op by op, each new K compiled a handful of programs.
    H = jax.random.normal(key, (3 * K, 3 * K), dtype) * coupling_mask(K, dtype)
    if K == 1:
        return H
    return H * (frobenius / jnp.linalg.norm(H))


def random_observation_matrix(
    key: PRNGKeyArray, K: int, m: int | None = None, dtype=jnp.float64
) -> Float[Array, "m n"]:
    """Standard-normal C ∈ R^{m×3K}, m = 3K − 2 by default (full row rank with probability one)."""
    m = 3 * K - 2 if m is None else m
    C = _standard_normal(key, (m, 3 * K), dtype)
    if np.linalg.matrix_rank(np.asarray(C)) < min(m, 3 * K):  # pragma: no cover - measure zero
        raise RuntimeError("drew a rank-deficient C; use another key")
    return C


def initial_states(
    key: PRNGKeyArray, B: int, K: int, dtype=jnp.float64, std: float = INITIAL_STD
) -> Float[Array, "B n"]:
    """(B, 3K) initial states from the paper's N((−6, −6, 24), std²) per attractor (std 2.5)."""
    return _initial_states(key, B, K, dtype, jnp.asarray(std, dtype))


@program(runs=Runs.ONCE)
def _standard_normal(key, shape: tuple[int, ...], dtype):
    return jax.random.normal(key, shape, dtype)


@program(runs=Runs.ONCE)
def _initial_states(key, B: int, K: int, dtype, std):
    mean = jnp.tile(jnp.asarray(INITIAL_MEAN, dtype), K)
    return mean[None, :] + std * jax.random.normal(key, (B, 3 * K), dtype)
