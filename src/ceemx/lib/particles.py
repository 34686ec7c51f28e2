"""Particle-method primitives: log-weights, effective sample size, resampling, backward sampling.

Nothing here knows about systems or EM: weights are log-weights over the last axis, particles are
indexed by integers. The user-facing particle filter and FFBSi (:mod:`ceemx.inference`) compose
these. Everything works under ``vmap`` and ``jit``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ceemx.lib.typing import Scalar

__all__ = [
    "backward_indices",
    "ess",
    "log_normalize",
    "offspring_counts",
    "systematic_resample",
]


def log_normalize(log_w: Float[Array, " N"]) -> tuple[Float[Array, " N"], Scalar]:
    """(log-weights normalised to sum to one, log Σ exp(log_w)).

    All weights −∞ (or NaN) give uniform weights and a log-sum of −∞ (NaN): the caller reads the
    failure from the returned log-sum, never from NaN weights.
    """
    total = jax.nn.logsumexp(log_w)
    ok = jnp.isfinite(total)
    uniform = -jnp.log(jnp.asarray(log_w.shape[-1], log_w.dtype))
    normed = jnp.where(ok, log_w - jnp.where(ok, total, 0.0), uniform)
    return normed, total


def ess(log_w: Float[Array, " N"]) -> Scalar:
    """Effective sample size 1 / Σ w̄ᵢ² of the normalised weights (between 1 and N)."""
    normed, _ = log_normalize(log_w)
    return jnp.exp(-jax.nn.logsumexp(2.0 * normed))


def systematic_resample(key: PRNGKeyArray, log_w: Float[Array, " N"], num: int | None = None):
    """Ancestor indices (num,) by systematic resampling of the weights exp(log_w) (normalised here).

    One uniform U ~ U(0, 1); the points (i + U)/num, i = 0…num−1, are mapped through the inverse
    CDF. Unbiased: particle i is drawn N·w̄ᵢ times in expectation, and always ⌊N·w̄ᵢ⌋ or ⌈N·w̄ᵢ⌉
    times. The returned indices are sorted (ancestors in order).
    """
    N = log_w.shape[-1]
    num = N if num is None else int(num)
    normed, _ = log_normalize(log_w)
    cdf = jnp.cumsum(jnp.exp(normed))
    cdf = cdf / cdf[-1]  # exact 1 at the end despite round-off
    u = (jnp.arange(num, dtype=log_w.dtype) + jax.random.uniform(key, (), log_w.dtype)) / num
    idx = jnp.searchsorted(cdf, u, side="right")
    return jnp.clip(idx, 0, N - 1).astype(jnp.int32)


def offspring_counts(ancestors: Int[Array, " k"], num_particles: int) -> Int[Array, " N"]:
    """How many times each of ``num_particles`` particles appears among ``ancestors``."""
    return jnp.zeros((num_particles,), jnp.int32).at[ancestors].add(1)


def backward_indices(
    key: PRNGKeyArray, log_w: Float[Array, " N"], log_trans: Float[Array, "S N"]
) -> Int[Array, " S"]:
    """One backward-simulation step of FFBSi for S trajectories at once.

    Draws, for each backward trajectory s, an index i with probability
    ∝ w_t^i · p(x̃_{t+1}^s | x_t^i), given the filter's log-weights ``log_w`` (N,) at t and
    ``log_trans[s, i]`` = log p(x̃_{t+1}^s | x_t^i). O(S·N).
    """
    logits = log_w[None, :] + log_trans
    return jax.random.categorical(key, logits, axis=-1).astype(jnp.int32)
