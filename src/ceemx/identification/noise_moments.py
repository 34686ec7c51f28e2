"""Expected residual second moments of the noise models, and their closed-form M-step.

Under a Gaussian posterior q over the states (the Laplace approximation at the MAP trajectory),
the expected residual second moments E_q[w_t w_tᵀ] of the dynamics and E_q[v_t v_tᵀ] of the
observations, summed by cubature over the marginal and pairwise posteriors
(:func:`noise_second_moments`), are the EM statistics of the noise covariances:
:func:`updated_noise` sets a Gaussian noise model to them (same class and leaf shapes). Laplace
EM's M-step learns noise with them; the noise estimate and the residual diagnostics
(:mod:`ceemx.identification.analysis`) read them. Long records are estimated from a first part of
them first (:func:`coarse_shape`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ceemx.data.trajectories import Trajectories
from ceemx.inference.objective import dynamics_weights, observed_span
from ceemx.infra.compilation import jit
from ceemx.lib.cubature import pair_points_first_half
from ceemx.lib.typing import PerTrajectory
from ceemx.models.noise import AbstractNoise, SecondMoments
from ceemx.models.system import AbstractSystem

__all__ = [
    "COARSE_FACTOR",
    "COARSE_STEPS",
    "NOISE_FIELDS",
    "coarse_shape",
    "field_moments",
    "noise_second_moments",
    "updated_noise",
]

#: the system's noise models, by field name
NOISE_FIELDS = ("process_noise", "obs_noise")

#: the default size (time steps, B·T) of the part of long data a coarse start fits first
COARSE_STEPS = 10_000
#: a coarse start runs when the data hold at least this many times ``coarse_start`` time steps
COARSE_FACTOR = 4


def coarse_shape(B: int, T: int, steps: int | None = COARSE_STEPS) -> tuple[int, int] | None:
    """(b, t) of the part of B records of T steps that a coarse start fits, or ``None``.

    ``None`` when ``steps`` is ``None`` or the data hold fewer than ``COARSE_FACTOR``·``steps``
    time steps; else the first b = ⌈steps / T⌉ records, each cut to its first ⌈steps / b⌉ steps.
    """
    if steps is None or B * T < COARSE_FACTOR * steps:
        return None
    b = min(B, -(-steps // T))
    return b, min(T, max(2, -(-steps // b)))


@jit
def noise_second_moments(
    system: AbstractSystem,
    points: Float[Array, "B T K n"],
    pairs: Float[Array, "B T-1 K2 n2"],
    data: Trajectories,
    weights: PerTrajectory,
) -> dict[str, Array]:
    """Weighted sums of the expected residual second moments under q (cubature).

    Returns a dict: ``dyn`` (n, n) Σ_b w_b Σ_t E[r^w_t r^wᵀ_t] and ``dyn_count`` Σ_b w_b (T_b−1),
    over the transitions up to each trajectory's last observation
    (:func:`~ceemx.inference.objective.dynamics_weights`: a shorter record's padding is left out);
    ``obs_diag`` (m,) Σ_b w_b Σ_t mask·E[(r^v_t)²] and ``obs_count`` (m,) Σ_b w_b Σ_t mask;
    ``obs_full`` (m, m) the same with missing components filled in from their conditional under
    the current observation noise where it couples them
    (:meth:`ceemx.AbstractNoise.masked_fill`; otherwise the unfilled moments) and
    ``obs_full_count`` Σ_b w_b T_b, over the steps up to each trajectory's last observation.
    """
    n = points.shape[-1]
    obs = system.obs_noise
    T = points.shape[1]
    ts = jnp.arange(T)

    def one(xp, zp, y, u, mask):
        def obs_step(xs, yt, ut, mk, t):
            v = jax.vmap(lambda x: jnp.where(mk, yt - system.observe(x, ut, t), 0.0))(xs)
            S = jnp.einsum("ki,kj->ij", v, v) / xs.shape[0]
            return S, obs.masked_fill(S, mk)

        S_obs, S_full = jax.vmap(obs_step)(xp, y, u, mask, ts)

        # the dynamics once per distinct x_t of the pair points (2n + 1 of 4n)
        first, spread = pair_points_first_half(zp, n)
        fx = jax.vmap(lambda xs, ut, t: jax.vmap(lambda x: system.dynamics(x, ut, t))(xs))(
            first, u[:-1], ts[:-1]
        )
        keep = dynamics_weights(mask)  # not the steps after the last observation
        r = jnp.where(keep[:, None, None], zp[..., n:] - spread(fx), 0.0)
        S_dyn = jnp.einsum("tki,tkj->tij", r, r) / zp.shape[1]
        diag = jnp.diagonal(S_obs, axis1=-2, axis2=-1)
        span = observed_span(mask)
        S_full = jnp.where(span[:, None, None], S_full, 0.0)
        counts = (keep.sum(), mask.sum(0), span.sum())
        counts = tuple(c.astype(xp.dtype) for c in counts)
        return S_dyn.sum(0), diag.sum(0), S_full.sum(0), *counts

    dyn, diag, full, dyn_count, count, full_count = jax.vmap(one)(
        points, pairs, data.y, data.u, data.mask
    )
    w = jnp.where(weights > 0, weights, 0.0)
    ok = weights > 0

    def wsum(a):
        shape = (-1,) + (1,) * (a.ndim - 1)
        return jnp.sum(jnp.where(ok.reshape(shape), w.reshape(shape) * a, 0.0), axis=0)

    return {
        "dyn": wsum(dyn),
        "dyn_count": wsum(dyn_count),
        "obs_diag": wsum(diag),
        "obs_count": wsum(count),
        "obs_full": wsum(full),
        "obs_full_count": wsum(full_count),
    }


def field_moments(field: str, moments: dict[str, Array]) -> SecondMoments:
    """The mean residual second moments of ``field`` from the sums of noise_second_moments."""
    if field == "process_noise":
        full = moments["dyn"] / moments["dyn_count"]
        diagonal = jnp.diagonal(full)
        return SecondMoments(full, diagonal, jnp.mean(diagonal))
    count = moments["obs_count"]
    return SecondMoments(
        full=moments["obs_full"] / moments["obs_full_count"],
        diagonal=moments["obs_diag"] / jnp.where(count > 0, count, 1.0),
        pooled=jnp.sum(moments["obs_diag"]) / jnp.sum(count),
        present=count > 0,
    )


def updated_noise(noise: AbstractNoise, field: str, moments: dict[str, Array]) -> AbstractNoise:
    """The noise model of ``field`` set to its closed-form M-step (same class and leaf shapes).

    Raises:
        TypeError: for a model without a closed-form update (``learnable_in_closed_form``).
    """
    return noise.covariance_update(field_moments(field, moments))
