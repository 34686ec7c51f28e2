"""State-space systems: x_{t+1} = f_θ(x_t, u_t, t) + w_t,  y_t = g_θ(x_t, u_t, t) + v_t  (Eq. 1)."""

from __future__ import annotations

import abc
from typing import TypeVar

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, ArrayLike, Float, Real

from ..typing import Scalar, State
from .noise import AbstractNoise, as_noise

__all__ = [
    "AbstractSystem",
    "AbstractContinuousSystem",
    "GaussianPrior",
    "float_dtype",
    "rk4_step",
    "with_noise",
]

_S = TypeVar("_S", bound="AbstractSystem")


class GaussianPrior(eqx.Module):
    """Initial-state prior x₁ ~ N(mean, Σ), Σ given by a noise model on the deviation x₁ − mean."""

    mean: State
    noise: AbstractNoise

    def nll(self, x1: State) -> Scalar:
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
    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """f_θ(x, u, t): the next state's mean (t: the integer time step)."""

    @abc.abstractmethod
    def observe(
        self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> Float[Array, " m"]:
        """g_θ(x, u, t): the observation's mean."""

    def linear_observation(
        self, u: Float[Array, " p"], t: Real[ArrayLike, ""]
    ) -> tuple[Float[Array, "m n"], Float[Array, " m"]] | None:
        """(C, d) when the observation is linear in x, g_θ(x, u, t) = C x + d; else ``None``.

        The default, ``None``, claims nothing. A system whose observation is linear in the state
        (for any u, t) overrides this; particle filters then use the fully adapted proposal
        p(x_t | x_{t−1}, y_t) in closed form (:func:`ceemx.particle_filter`). The structure (None
        or a pair) must not depend on the values of u and t.
        """
        return None

    def check(self) -> None:
        """Host-side validation of the noise models (raises ``ValueError`` naming the field)."""
        self.process_noise.check("system.process_noise")
        self.obs_noise.check("system.obs_noise")
        if self.initial_prior is not None:
            self.initial_prior.noise.check("system.initial_prior.noise")


def float_dtype(tree) -> jnp.dtype:
    """The dtype of the first floating-point array of ``tree`` (a system's working precision).

    Noise models and initial-state priors are skipped (for a system: the dtype of its model
    parameters θ). Falls back to JAX's default float dtype when there is no such array.
    """
    skip = lambda x: isinstance(x, AbstractNoise | GaussianPrior)  # noqa: E731
    for leaf in jtu.tree_leaves(tree, is_leaf=skip):
        if not skip(leaf) and eqx.is_inexact_array(leaf):
            return leaf.dtype
    return jnp.zeros(()).dtype


def with_noise(
    system: _S,
    process_noise: AbstractNoise | ArrayLike | None = None,
    obs_noise: AbstractNoise | ArrayLike | None = None,
) -> _S:
    """The same system with other noise models (the weights of the residuals in J, Eq. 9).

    Args:
        system: any system.
        process_noise: the new p_w: a noise model, or a scale (scalar or length-n vector of
            standard deviations) for ``DiagonalGaussian(scale, n)``; ``None`` keeps the current one.
        obs_noise: the new p_v, likewise (length-m scales).

    Returns:
        A copy of ``system``; scales are cast to the system's floating-point dtype
        (:func:`float_dtype`), noise models are used as given.
    """
    dtype = float_dtype(system)

    def make(value, current, dim):
        if value is None:
            return current
        if not isinstance(value, AbstractNoise):
            value = jnp.asarray(value, dtype)
        return as_noise(value, dim)

    pn = make(process_noise, system.process_noise, system.state_dim)
    on = make(obs_noise, system.obs_noise, system.obs_dim)
    return eqx.tree_at(lambda s: (s.process_noise, s.obs_noise), system, (pn, on))


def rk4_step(vector_field, x, u, t, dt):
    """One classic fourth-order Runge–Kutta step of ẋ = F(x, u, t), u constant over the step."""
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
    def vector_field(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """F_θ(x, u, t), the continuous-time derivative of the state (t: continuous time)."""

    def default_state_mean(self) -> State | None:
        """A typical state (n,), or ``None`` (the default) when the system has none.

        :func:`ceemx.evaluate.dynamics_error` compares vector fields at states sampled around it
        unless given a ``mean``.
        """
        return None

    def dynamics(self, x: State, u: Float[Array, " p"], t: Real[ArrayLike, ""]) -> State:
        """One RK4 step of length ``dt`` from time t·dt."""
        return rk4_step(self.vector_field, x, u, jnp.asarray(t, x.dtype) * self.dt, self.dt)
