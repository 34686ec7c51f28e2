"""The learning step's Gauss–Newton matrix as one product of the batch's whitened θ-Jacobian rows.

At fixed states, −J_b(θ) is a sum of per-step factors (observations, transitions, the initial
prior). The Gauss–Newton matrix of Σ_b w_b (−J_b) is Σ_b w_b Σ_rows (S J_θ)ᵀ (S J_θ) with each
factor's curvature root S (:mod:`ceemx.models.noise`). Here the rows of every trajectory, scaled
by √w_b, are stacked into one (R, P) matrix and the P × P matrix is formed by a single product
RᵀR — not one P × P product per trajectory summed afterwards — and factors whose residual does not
depend on θ at all (the observation model when only the dynamics learn, or the reverse) contribute
no rows: that is decided at trace time from the residual's program
(:func:`ceemx.inference.objective.depends_on`), since
the θ-Jacobian of such a factor is identically zero and its product would be pure cost (on the
Figure-3 problem half of the build).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ceemx.inference.objective import auto_jacobian, depends_on, residuals
from ceemx.lib.typing import Scalar, Theta, Trajectory
from ceemx.models.system import AbstractSystem

__all__ = ["gram", "theta_rows"]


def theta_rows(
    build: Callable[[Theta], AbstractSystem],
    theta: Theta,
    x: Trajectory,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
) -> tuple[Scalar, Float[Array, " theta"], Float[Array, "R theta"]]:
    """(−J, its θ-gradient, the whitened θ-Jacobian rows S·J_θ) of one trajectory at fixed x.

    The rows are those of the observation factors (T·m) and of the transitions ((T−1)·n), each
    block present only when its residual depends on θ; RᵀR is the trajectory's Gauss–Newton matrix
    (that of ``inference.objective.linearize(..., wrt_theta=True)``). A prior whose mean depends
    on θ enters the value and the gradient, not the rows (as in ``linearize``).
    """
    system = build(theta)
    T, n = x.shape
    m, P = y.shape[-1], theta.shape[0]
    ts = jnp.arange(T)
    dtype = x.dtype

    def obs_res(xt, th, yt, ut, t):
        return yt - build(th).observe(xt, ut, t)

    def dyn_res(xt, th, ut, t):
        return -build(th).dynamics(xt, ut, t)  # + x_{t+1}, which does not depend on θ

    r_obs, r_dyn = residuals(system, x, y, u)
    on, pn = system.obs_noise, system.process_noise
    value = jnp.sum(jax.vmap(on.nll)(r_obs, mask)) + jnp.sum(jax.vmap(pn.nll)(r_dyn))
    grad = jnp.zeros((P,), dtype)
    rows = []
    if depends_on(obs_res, 1, x[0], theta, y[0], u[0], ts[0]):
        Gt = jax.vmap(auto_jacobian(obs_res, 1, P, m), in_axes=(0, None, 0, 0, 0))(
            x, theta, y, u, ts
        )
        grad = grad + jnp.einsum("tmp,tm->p", Gt, jax.vmap(jax.grad(on.nll))(r_obs, mask))
        if on.diagonal_curvature:
            SGt = jax.vmap(on.sqrt_curvature_diagonal)(r_obs, mask)[..., None] * Gt
        else:
            SGt = jax.vmap(on.sqrt_curvature)(r_obs, mask) @ Gt
        rows.append(SGt.reshape(-1, P))
    if T > 1 and depends_on(dyn_res, 1, x[0], theta, u[0], ts[0]):
        Ft = jax.vmap(auto_jacobian(dyn_res, 1, P, n), in_axes=(0, None, 0, 0))(
            x[:-1], theta, u[:-1], ts[:-1]
        )
        grad = grad + jnp.einsum("tnp,tn->p", Ft, jax.vmap(jax.grad(pn.nll))(r_dyn))
        if pn.diagonal_curvature:
            SFt = jax.vmap(pn.sqrt_curvature_diagonal)(r_dyn)[..., None] * Ft
        else:
            SFt = jax.vmap(pn.sqrt_curvature)(r_dyn) @ Ft
        rows.append(SFt.reshape(-1, P))
    prior = system.initial_prior
    if prior is not None:
        value = value + prior.nll(x[0])

        def prior_nll(th):
            pr = build(th).initial_prior
            assert pr is not None  # θ does not decide whether there is a prior
            return pr.nll(x[0])

        grad = grad + jax.grad(prior_nll)(theta)
    out = jnp.concatenate(rows) if rows else jnp.zeros((0, P), dtype)
    return value, grad, out.astype(dtype)


def gram(rows: Float[Array, "R theta"]) -> Float[Array, "theta theta"]:
    """RᵀR, symmetrised (one matrix product; zeros when R has no rows)."""
    D = rows.T @ rows
    return 0.5 * (D + D.T)
