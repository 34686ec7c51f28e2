"""State-space systems: x_{t+1} = f_θ(x_t, u_t, t) + w_t,  y_t = g_θ(x_t, u_t, t) + v_t  (Eq. 1)."""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .noise import AbstractNoise

__all__ = ["AbstractSystem", "AbstractContinuousSystem", "GaussianPrior", "rk4_step"]


class GaussianPrior(eqx.Module):
    """Initial-state prior x₁ ~ N(mean, Σ), Σ given by a noise model on the deviation x₁ − mean."""

    mean: Float[Array, " n"]
    noise: AbstractNoise

    def nll(self, x1: Float[Array, " n"]) -> Array:
        """−log p(x₁)."""
        return self.noise.nll(x1 - self.mean)


class AbstractSystem(eqx.Module):
    """A discrete-time partially observed system with additive noise (paper Eq. 1).

    Subclasses define the model class f_θ, g_θ; their array fields are the parameters θ (which of
    them are learned is chosen at fit time by a filter). Attributes every system provides:

    Attributes:
        process_noise: density p_w of w_t = x_{t+1} − f_θ(x_t, u_t, t).
        obs_noise: density p_v of v_t = y_t − g_θ(x_t, u_t, t).
        initial_prior: optional prior on x₁ (``None``: flat).
    """

    process_noise: eqx.AbstractVar[AbstractNoise]
    obs_noise: eqx.AbstractVar[AbstractNoise]
    initial_prior: eqx.AbstractVar[GaussianPrior | None]

    @property
    @abc.abstractmethod
    def state_dim(self) -> int:
        """n, the dimension of x."""

    @property
    @abc.abstractmethod
    def obs_dim(self) -> int:
        """m, the dimension of y."""

    @property
    def input_dim(self) -> int:
        """p, the dimension of u (0 when the system has no input)."""
        return 0

    @abc.abstractmethod
    def dynamics(self, x: Float[Array, " n"], u: Float[Array, " p"], t: Array) -> Array:
        """f_θ(x, u, t): the next state's mean."""

    @abc.abstractmethod
    def observe(self, x: Float[Array, " n"], u: Float[Array, " p"], t: Array) -> Array:
        """g_θ(x, u, t): the observation's mean."""

    def check(self) -> None:
        """Host-side validation of the noise models (raises ``ValueError`` naming the field)."""
        self.process_noise.check("system.process_noise")
        self.obs_noise.check("system.obs_noise")
        if self.initial_prior is not None:
            self.initial_prior.noise.check("system.initial_prior.noise")


def rk4_step(vector_field, x, u, t, dt):
    """One classic fourth-order Runge–Kutta step of ẋ = F(x, u, t), u held constant over the step."""
    k1 = vector_field(x, u, t)
    k2 = vector_field(x + 0.5 * dt * k1, u, t + 0.5 * dt)
    k3 = vector_field(x + 0.5 * dt * k2, u, t + 0.5 * dt)
    k4 = vector_field(x + dt * k3, u, t + dt)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


class AbstractContinuousSystem(AbstractSystem):
    """A continuous-time vector field ẋ = F_θ(x, u, t) discretised by classic RK4 with fixed ``dt``.

    f_θ(x_t, u_t, t) = RK4(F_θ, x_t, u_t, t·dt, dt) with u held constant over the step (zero-order
    hold). Subclasses implement :meth:`vector_field` and set ``dt``.
    """

    dt: eqx.AbstractVar[float]

    @abc.abstractmethod
    def vector_field(self, x: Float[Array, " n"], u: Float[Array, " p"], t: Array) -> Array:
        """F_θ(x, u, t), the continuous-time derivative of the state."""

    def dynamics(self, x, u, t):
        """One RK4 step of length ``dt`` from time t·dt."""
        return rk4_step(self.vector_field, x, u, jnp.asarray(t, x.dtype) * self.dt, self.dt)
