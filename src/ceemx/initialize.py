"""Initial state trajectories when the user has none."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .data import Trajectories, rollout_one
from .models.system import AbstractSystem

__all__ = ["from_observations", "rollout"]


@eqx.filter_jit
def from_observations(
    system: AbstractSystem, data: Trajectories, x_guess=None, ridge: float = 1e-6
):
    """States by least squares through the observation map linearised at ``x_guess``.

    Per step, x_t = x̄ + argmin_δ ‖S(y_t − g(x̄) − G δ)‖² + ridge·‖δ‖² over the observed
    components, with G = ∂g/∂x at x̄ (``x_guess``, default zeros) and S the observation noise's
    whitening. Unobservable directions stay at x̄ (minimum-norm solution). Use it to start the
    smoother, which then reconciles the states with the dynamics.

    Returns:
        (B, T, n) states.
    """
    B, T, _ = data.y.shape
    n = system.state_dim
    dtype = data.y.dtype
    xbar = jnp.zeros((n,), dtype) if x_guess is None else jnp.asarray(x_guess, dtype)

    def one(y, u, mask, t):
        g0 = system.observe(xbar, u, t)
        G = jax.jacfwd(system.observe)(xbar, u, t)
        S = system.obs_noise.sqrt_curvature(y - g0, mask)
        A = S @ G
        b = S @ jnp.where(mask, y - g0, 0.0)
        lhs = (
            A.T @ A
            + ridge * jnp.trace(A.T @ A) / n * jnp.eye(n, dtype=dtype)
            + 1e-30 * jnp.eye(n, dtype=dtype)
        )
        return xbar + jnp.linalg.solve(lhs, A.T @ b)

    ts = jnp.broadcast_to(jnp.arange(T), (B, T))
    return jax.vmap(jax.vmap(one))(data.y, data.u, data.mask, ts)


@eqx.filter_jit
def rollout(system: AbstractSystem, data: Trajectories, x1):
    """States by simulating the noise-free dynamics from guessed initial states ``x1`` (B, n)."""
    return jax.vmap(lambda x0, u: rollout_one(system, x0, u))(jnp.asarray(x1, data.y.dtype), data.u)
