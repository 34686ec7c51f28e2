"""The extended Kalman filter of any system with Gaussian noise (one-step prediction, paper §4.2.4).

For x_{t+1} = f(x_t, u_t, t) + w_t, y_t = g(x_t, u_t, t) + v_t with w_t ~ N(0, Q), v_t ~ N(0, R)
and a Gaussian prior x₁ ~ N(x̂_{1|0}, P_{1|0}), each step t = 0, …, T−1 (ceemx's integer time
index) does, with G_t = ∂g/∂x and F_t = ∂f/∂x by forward-mode autodiff:

    predict y:  ŷ_t = g(x̂_{t|t−1}, u_t, t),   S_t = G_t P_{t|t−1} G_tᵀ + R     (recorded first)
    correct:    K_t = P_{t|t−1} G_tᵀ S_t⁻¹ (present components of y_t only),
                x̂_{t|t} = x̂_{t|t−1} + K_t (y_t − ŷ_t),
                P_{t|t} = (I − K_t G_t) P_{t|t−1} (I − K_t G_t)ᵀ + K_t R K_tᵀ  (Joseph form)
    predict x:  x̂_{t+1|t} = f(x̂_{t|t}, u_t, t),  P_{t+1|t} = F_t P_{t|t} F_tᵀ + Q.

So ŷ_t depends on u_{1:t} and y_{1:t−1} only: it is the model's one-step-ahead prediction.
Missing components of y_t (the data's mask) drop out of the correction and the likelihood
exactly (:func:`ceemx.lib.kalman.gaussian_update`). On a linear-Gaussian model the filter is the
Kalman filter and its log-likelihood the exact log p(y_{1:T}).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ceemx.data.checks import prepare, promote_tree
from ceemx.data.trajectories import Trajectories
from ceemx.infra.compilation import jit
from ceemx.lib import kalman
from ceemx.lib.dense import cholesky, symmetrize
from ceemx.lib.results import RESULTS, select
from ceemx.lib.typing import Observations, PerTrajectory, Scalar, States, no_type_check
from ceemx.models.noise import AbstractGaussianNoise, DiagonalGaussian
from ceemx.models.system import AbstractSystem, GaussianPrior, float_dtype

__all__ = ["FilterSolution", "ekf"]


class FilterSolution(eqx.Module):
    """The output of :func:`ekf` for B trajectories of T steps (state n, observation m).

    Attributes:
        predicted_obs: (B, T, m) one-step predictions ŷ_t = g(x̂_{t|t−1}, u_t, t).
        innovation_chol: (B, T, m, m) lower Cholesky factor of the innovation covariance
            S_t = G_t P_{t|t−1} G_tᵀ + R over all m components (whether observed or not): the
            predictive covariance of y_t.
        predicted_means: (B, T, n) x̂_{t|t−1} (t = 0: the prior mean).
        filtered_means: (B, T, n) x̂_{t|t}.
        filtered_chol: (B, T, n, n) lower Cholesky factor of P_{t|t}.
        log_likelihood: (B,) Σ_t log N(y_t; ŷ_t, S_t) over the present components of each y_t
            (exact log p(y_{1:T}) for a linear-Gaussian model).
        status: (B,) :class:`ceemx.RESULTS`: ``successful``, or ``nonfinite`` when a covariance
            stopped being positive definite or a mean or prediction became non-finite. The
            outputs of such a trajectory are NaN from the first failing step on, and its
            ``log_likelihood`` is NaN.
    """

    predicted_obs: Observations
    innovation_chol: Float[Array, "B T m m"]
    predicted_means: States
    filtered_means: States
    filtered_chol: Float[Array, "B T n n"]
    log_likelihood: PerTrajectory
    status: RESULTS


def _value_and_jacobian(fn, x: Float[Array, " n"]):
    """(fn(x), ∂fn/∂x) in one forward-mode pass."""

    def both(z):
        out = fn(z)
        return out, out

    jac, value = jax.jacfwd(both, has_aux=True)(x)
    return value, jac


def _all_finite(*arrays) -> Bool[Array, ""]:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in arrays]))


def _ekf_one(
    system: AbstractSystem,
    prior: GaussianPrior,
    y: Float[Array, "T m"],
    u: Float[Array, "T p"],
    mask: Bool[Array, "T m"],
):
    """The filter on one trajectory (see :func:`ekf`)."""
    dtype = y.dtype
    T = y.shape[0]
    L_Q = system.process_noise.cholesky().astype(dtype)  # type: ignore[attr-defined]
    L_R = system.obs_noise.cholesky().astype(dtype)  # type: ignore[attr-defined]
    R = L_R @ L_R.T
    Q = L_Q @ L_Q.T
    m0 = prior.mean.astype(dtype)
    P0 = prior.noise.covariance().astype(dtype)  # type: ignore[attr-defined]

    def step(carry, inp):
        x_pred, P_pred, ok = carry
        yt, ut, mt, t = inp
        y_hat, G = _value_and_jacobian(lambda x: system.observe(x, ut, t), x_pred)
        y_hat, G = y_hat.astype(dtype), G.astype(dtype)
        chol_S = cholesky(symmetrize(G @ P_pred @ G.T + R))
        up = kalman.gaussian_update(P_pred, G, L_R, mt)
        # gaussian_update's mean is μ + K (y − G μ): pass y − ŷ + G μ for K (y − ŷ).
        y_eff = yt - y_hat + G @ x_pred
        x_filt = up.mean(x_pred, y_eff)
        ll = kalman.predictive_log_density(up, x_pred, y_eff)
        ok = ok & _all_finite(x_pred, P_pred, y_hat, chol_S, x_filt, up.chol_post, ll)
        x_next, F = _value_and_jacobian(lambda x: system.dynamics(x, ut, t), x_filt)
        FL = F.astype(dtype) @ up.chol_post
        P_next = symmetrize(FL @ FL.T + Q)
        nan = jnp.asarray(jnp.nan, dtype)
        out = jax.tree_util.tree_map(
            lambda a: jnp.where(ok, a, nan), (y_hat, chol_S, x_pred, x_filt, up.chol_post, ll)
        )
        return (x_next.astype(dtype), P_next, ok), out

    ts = jnp.arange(T)
    init = (m0, symmetrize(P0), jnp.asarray(True))
    (_, _, ok), outs = jax.lax.scan(step, init, (y, u, mask, ts))
    y_hat, chol_S, x_pred, x_filt, chol_f, ll = outs
    log_lik: Scalar = jnp.where(ok, jnp.sum(ll), jnp.asarray(jnp.nan, dtype))
    return y_hat, chol_S, x_pred, x_filt, chol_f, log_lik, ok


@jit
def ekf_batch(system: AbstractSystem, data: Trajectories, prior: GaussianPrior) -> FilterSolution:
    """The compiled kernel of :func:`ekf` (no validation; ``prior`` resolved)."""
    out = jax.vmap(lambda y, u, m: _ekf_one(system, prior, y, u, m))(data.y, data.u, data.mask)
    y_hat, chol_S, x_pred, x_filt, chol_f, log_lik, ok = out
    status = select(ok, RESULTS.successful, RESULTS.nonfinite)
    return FilterSolution(y_hat, chol_S, x_pred, x_filt, chol_f, log_lik, status)


def _check_gaussian(noise, name: str) -> None:
    if not isinstance(noise, AbstractGaussianNoise):
        raise TypeError(
            f"the extended Kalman filter needs Gaussian noise, but `{name}` is "
            f"{type(noise).__name__}; use a DiagonalGaussian or CholeskyGaussian."
        )


def _check_factor(noise: AbstractGaussianNoise, name: str, dim: int, dim_name: str) -> None:
    try:
        shape = tuple(np.shape(noise.cholesky()))
    except (TypeError, ValueError):  # e.g. a DiagonalGaussian whose scale has the wrong length
        shape = None
    if shape != (dim, dim):
        raise ValueError(
            f"`{name}` has a covariance of shape {shape or 'unknown'}; the system needs "
            f"({dim}, {dim}) ({dim_name} = {dim})."
        )


def _resolve_prior(system: AbstractSystem, initial: GaussianPrior | None, dtype) -> GaussianPrior:
    """``initial``, else the system's prior, else N(0, I); validated on the host."""
    n = system.state_dim
    if initial is not None:
        prior, name = initial, "initial"
    elif system.initial_prior is not None:
        prior, name = system.initial_prior, "system.initial_prior"
    else:
        return GaussianPrior(jnp.zeros((n,), dtype), DiagonalGaussian(jnp.ones((), dtype), n))
    if not isinstance(prior, GaussianPrior):
        raise TypeError(f"`{name}` must be a ceemx.GaussianPrior; got {type(prior).__name__}.")
    mean = np.asarray(prior.mean)
    if mean.shape != (n,) or not np.all(np.isfinite(mean)):
        raise ValueError(
            f"`{name}.mean` must be a finite vector of length n = {n}; got shape {mean.shape}."
        )
    _check_gaussian(prior.noise, name + ".noise")
    prior.noise.check(name + ".noise")
    _check_factor(prior.noise, name + ".noise", n, "n")  # type: ignore[arg-type]
    return prior


@no_type_check  # validates its arguments: prepare and the checks below
def ekf(
    system: AbstractSystem, data: Trajectories, *, initial: GaussianPrior | None = None
) -> FilterSolution:
    """Extended Kalman filter on every trajectory of ``data`` at the system's θ.

    Per step t (0-based, as the system's time argument): the one-step prediction
    ŷ_t = g(x̂_{t|t−1}, u_t, t) and its covariance S_t = G P_{t|t−1} Gᵀ + R are recorded, then the
    present components of y_t correct the state (masked Joseph-form update,
    :func:`ceemx.lib.kalman.gaussian_update`), then x̂_{t+1|t} = f(x̂_{t|t}, u_t, t) and
    P_{t+1|t} = F P_{t|t} Fᵀ + Q. G and F are Jacobians by ``jax.jacfwd``. See the module
    docstring for the equations.

    Args:
        system: the model. Its ``process_noise`` (Q) and ``obs_noise`` (R) must be Gaussian
            (:class:`ceemx.AbstractGaussianNoise`).
        data: B trajectories of observations, inputs and masks.
        initial: the prior N(x̂_{1|0}, P_{1|0}) on x₁ (Gaussian noise). ``None``: the system's
            ``initial_prior``, or N(0, I) when it has none (the authors' evaluation).

    Data and ``initial`` are cast to the dtype of the system's parameters, as by :func:`ceemx.fit`
    and :func:`ceemx.smooth` (:func:`ceemx.data.checks.promote_inputs`).

    Returns:
        A :class:`FilterSolution` (arrays in the system's dtype). A trajectory whose covariances
        stop being positive definite or whose means become non-finite gets status ``nonfinite``
        and NaN outputs from that step on; the others are unaffected. Trajectories are
        independent (``vmap`` over the batch, ``lax.scan`` over time); compiled once per shape.

    Raises:
        TypeError: ``data`` is not a :class:`ceemx.Trajectories`, or a noise model or the prior
            is not Gaussian (the message names ``system.process_noise``, ``system.obs_noise`` or
            ``initial``).
        ValueError: mismatched dimensions, a float16 system, a value that overflows the cast, or
            invalid noise parameters, before any compute.

    Example:
        >>> sol = ceemx.inference.ekf.ekf(system, data)  # doctest: +SKIP
        >>> sol.predicted_obs.shape  # (B, T, m)  # doctest: +SKIP
    """
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"`system` must be a ceemx.AbstractSystem; got {type(system).__name__}.")
    inputs = prepare(system, data)  # one dtype: the system's, as fit and smooth
    system, data = inputs.system, inputs.data
    if initial is not None:
        initial = promote_tree(initial, system)
    return ekf_prepared(system, data, initial)


def ekf_prepared(
    system: AbstractSystem, data: Trajectories, initial: GaussianPrior | None = None
) -> FilterSolution:
    """:func:`ekf` of prepared inputs (:func:`ceemx.data.checks.prepare`; ``initial`` promoted).

    The noise models and the prior are checked here; the system and data are not again.
    """
    _check_gaussian(system.process_noise, "system.process_noise")
    _check_gaussian(system.obs_noise, "system.obs_noise")
    _check_factor(system.process_noise, "system.process_noise", system.state_dim, "n")  # type: ignore[arg-type]
    _check_factor(system.obs_noise, "system.obs_noise", system.obs_dim, "m")  # type: ignore[arg-type]
    prior = _resolve_prior(system, initial, jnp.dtype(float_dtype(system)))
    return ekf_batch(system, data, prior)
