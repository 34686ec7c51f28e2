"""A stiff, partially observed three-state mechanical model with a hidden hysteretic force.

A mass on a spring and damper with a Bouc–Wen hysteretic restoring force z that is not measured:
x = (position q, velocity q̇, hysteretic force z), only q is observed (SI units, metres),

    q̈ = (u − k q − c q̇ − z) / m,   ż = α q̇ − β |q̇| z − γ q̇ |z|   (ν = 1),   y = q + v.

The values are those of the Bouc–Wen benchmark's model (m = 2 kg, k = α = 5·10⁴ N/m, 35 Hz,
β|q̇| up to a few hundred s⁻¹; sampled at 750 Hz, RK4 with substeps), and, like that benchmark's
records, the process noise is small against the observation noise: the record on which a learned
observation noise collapses (the Laplace evidence keeps rising as σ_v → 0 and the states
interpolate the data). The mass is known (fixed); c, k, α, β, γ are learned.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import ceemx

TRUE = dict(c=10.0, k=5.0e4, alpha=5.0e4, beta=800.0, gamma=-1100.0)
PROCESS_STD = np.array([1e-9, 1e-6, 1e-3])
OBS_STD = 8e-6
DT = 1.0 / 750.0
#: the input force's RMS (N)
FORCE_RMS = 50.0


class BoucWen(ceemx.AbstractContinuousSystem):
    """Mass–spring–damper with a hidden Bouc–Wen hysteretic force; y = position."""

    c: jax.Array = ceemx.param(positive=True)
    k: jax.Array = ceemx.param(positive=True)
    alpha: jax.Array = ceemx.param(positive=True)
    beta: jax.Array = ceemx.param(positive=True)
    gamma: jax.Array = ceemx.param()
    mass: jax.Array = ceemx.param(fixed=True, default=2.0)

    state_dim = 3
    obs_dim = 1
    control_dim = 1

    def vector_field(self, x, u, t):
        q, v, z = x[0], x[1], x[2]
        dv = (u[0] - self.k * q - self.c * v - z) / self.mass
        dz = self.alpha * v - self.beta * jnp.abs(v) * z - self.gamma * v * jnp.abs(z)
        return jnp.stack([v, dv, dz])

    def observe(self, x, u, t):
        return x[:1]


def make(theta=None, process_std=PROCESS_STD, obs_std=OBS_STD, dtype=jnp.float64):
    theta = TRUE if theta is None else theta
    return BoucWen(
        **{k: jnp.asarray(v, dtype) for k, v in theta.items()},
        dt=DT,
        substeps=4,
        process_noise=jnp.asarray(process_std, dtype),
        obs_noise=jnp.asarray(obs_std, dtype),
    )


def inputs(seed, B, T):
    """Random-phase multisines, 5–150 Hz, RMS :data:`FORCE_RMS` (persistently exciting)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    freqs = np.arange(5.0, 150.0, 750.0 / 2048.0)
    out = np.empty((B, T, 1))
    for b in range(B):
        phases = rng.uniform(0, 2 * np.pi, freqs.size)
        s = np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases[None, :]).sum(axis=1)
        out[b, :, 0] = FORCE_RMS * s / np.sqrt(np.mean(s**2))
    return jnp.asarray(out)


def simulate(seed, B=1, T=1000, system=None, quantum=None):
    """(Trajectories, true states) from the true model with its noise (or ``system``).

    ``quantum``: the outputs rounded to multiples of it (an encoder's step), after the noise.
    """
    system = make() if system is None else system
    u = inputs(seed, B, T)
    x, data = ceemx.simulate(system, jax.random.PRNGKey(seed), jnp.zeros((B, 3)), T, u)
    if quantum is not None:
        data = ceemx.Trajectories(jnp.round(data.y / quantum) * quantum, data.u, data.mask)
    return data, x


def perturbed(seed, frac=0.3):
    """θ started ±frac (uniform) around the truth."""
    rng = np.random.default_rng(seed)
    return {name: float(v * (1 + rng.uniform(-frac, frac))) for name, v in TRUE.items()}
