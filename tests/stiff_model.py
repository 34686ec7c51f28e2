"""A stiff, partially observed three-state gray-box model with a hidden internal force.

A mass on a spring and damper driven through a fast first-order actuator whose force is not
measured: x = (position p, velocity v, actuator force F), only p is observed,

    ṗ = v,   v̇ = (F − k p − c v) / M,   Ḟ = (g u − F) / τ,   y = p.

τ = 0.05 s against a 0.63 s oscillation period makes it stiff (RK4 with substeps). The mass M is
known (fixed); k, c, g, τ are learned. Used by the noise-without-guessing tests.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import ceemx

TRUE = dict(k=100.0, c=2.0, g=50.0, tau=0.05)
PROCESS_STD = np.array([1e-4, 2e-2, 2e-1])
OBS_STD = 2e-3
DT = 0.02


class StiffActuator(ceemx.AbstractContinuousSystem):
    """Mass–spring–damper (known mass) driven by a fast hidden actuator force; y = position."""

    k: jax.Array = ceemx.param(positive=True)
    c: jax.Array = ceemx.param(positive=True)
    g: jax.Array = ceemx.param(positive=True)
    tau: jax.Array = ceemx.param(positive=True)
    mass: jax.Array = ceemx.param(fixed=True, default=1.0)

    state_dim = 3
    obs_dim = 1
    control_dim = 1

    def vector_field(self, x, u, t):
        p, v, f = x[0], x[1], x[2]
        dv = (f - self.k * p - self.c * v) / self.mass
        df = (self.g * u[0] - f) / self.tau
        return jnp.stack([v, dv, df])

    def observe(self, x, u, t):
        return x[:1]


def make(theta=None, process_std=PROCESS_STD, obs_std=OBS_STD, dtype=jnp.float64):
    theta = TRUE if theta is None else theta
    return StiffActuator(
        **{k: jnp.asarray(v, dtype) for k, v in theta.items()},
        dt=DT,
        substeps=4,
        process_noise=jnp.asarray(process_std, dtype),
        obs_noise=jnp.asarray(obs_std, dtype),
    )


def inputs(key, B, T):
    """Smoothed random steps (a persistently exciting, band-limited input)."""
    steps = jax.random.normal(key, (B, T // 10 + 1, 1))
    return jnp.repeat(steps, 10, axis=1)[:, :T]


def simulate(key, B=2, T=1000):
    """(true system, Trajectories) from the true model with its noise."""
    k1, k2 = jax.random.split(key)
    true = make()
    u = inputs(k1, B, T)
    x, data = ceemx.simulate(true, k2, jnp.zeros((B, 3)), T, u)
    return true, data, x


def perturbed(key, frac=0.3):
    """θ started ±frac (uniform) around the truth."""
    ks = jax.random.split(key, len(TRUE))
    return {
        name: float(v * (1 + jax.random.uniform(kk, minval=-frac, maxval=frac)))
        for (name, v), kk in zip(TRUE.items(), ks, strict=True)
    }
