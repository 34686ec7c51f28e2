"""Linear-Gaussian state-space model (the exact case of Kalman/RTS smoothing)."""

from __future__ import annotations

import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ceemx.lib.tree import as_jax
from ceemx.lib.typing import State
from ceemx.models.noise import AbstractNoise, as_noise
from ceemx.models.system import AbstractSystem, GaussianPrior

__all__ = ["LinearSystem"]


class LinearSystem(AbstractSystem):
    """x_{t+1} = A x_t + B u_t + w_t,  y_t = C x_t + D u_t + v_t.

    Attributes:
        A: (n, n) transition; B: (n, p) input; C: (m, n) observation; D: (m, p) feedthrough.
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n p"]
    C: Float[Array, "m n"]
    D: Float[Array, "m p"]

    def __init__(
        self,
        A,
        C,
        B=None,
        D=None,
        *,
        process_noise: AbstractNoise | ArrayLike = 1.0,
        obs_noise: AbstractNoise | ArrayLike = 1.0,
        initial_prior: GaussianPrior | None = None,
    ):
        # as_jax and NumPy zeros: a transfer where jnp.asarray / jnp.zeros compiled a program.
        self.A = as_jax(A)
        self.C = as_jax(C)
        n, m = self.A.shape[0], self.C.shape[0]
        if self.A.shape != (n, n):
            raise ValueError(f"`A` must be square; got shape {self.A.shape}.")
        if self.C.shape != (m, n):
            raise ValueError(f"`C` must have shape (m, {n}); got {self.C.shape}.")
        self.B = as_jax(np.zeros((n, 0), self.A.dtype)) if B is None else as_jax(B)
        p = self.B.shape[1]
        self.D = as_jax(np.zeros((m, p), self.A.dtype)) if D is None else as_jax(D)
        if self.B.shape != (n, p) or self.D.shape != (m, p):
            raise ValueError(
                f"`B` must be ({n}, p) and `D` ({m}, p); got {self.B.shape}, {self.D.shape}."
            )
        self.process_noise = as_noise(process_noise, n)
        self.obs_noise = as_noise(obs_noise, m)
        self.initial_prior = initial_prior

    @property
    def state_dim(self) -> int:
        """The state dimension n."""
        return self.A.shape[0]

    @property
    def obs_dim(self) -> int:
        """The observation dimension m."""
        return self.C.shape[0]

    @property
    def input_dim(self) -> int:
        """The input dimension p."""
        return self.B.shape[1]

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """A x + B u."""
        return self.A @ x + self.B @ u

    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """C x + D u."""
        return self.C @ x + self.D @ u

    def linear_observation(
        self, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> tuple[Float[Array, "m n"], Float[Array, " m"]]:
        """(C, D u): the observation is linear in the state."""
        return self.C, self.D @ u
