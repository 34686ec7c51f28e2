"""Run a representative set of ceemx's compiled programs (small sizes), for the LAPACK audit.

``.ci/check_lapack_concurrency.py`` runs this script with ``XLA_FLAGS=--xla_dump_to=DIR
--xla_dump_hlo_as_text`` and audits every optimised module XLA compiled. What runs: every fit
solver (Alternating with the LM and L-BFGS learners, JointLM, LaplaceEM with diagonal and full
learned noise covariances and missing observations, ParticleEM), MAP smoothing with covariances,
the EKF, the particle filter and FFBSi, free runs, x̂₁ estimation, k-step prediction, and the
parameter covariances (Schur complement after the CE methods, the evidence covariance after
Laplace EM), and smoothing and a joint fit with blocks above ``UNROLL_MAX`` (coupled Lorenz,
n = 9 and 48: LAPACK per step). Sizes are small but every scan runs more than one step, so the
compiled programs have the structure of large ones.

Usage: ``python .ci/lapack_programs.py [--quick]`` (``--quick``: Laplace EM only).
"""

from __future__ import annotations

import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import ceemx
from ceemx.data.trajectories import foh_inputs
from ceemx.systems import (
    CoupledLorenz,
    LinearSystem,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

jax.config.update("jax_enable_x64", True)
warnings.simplefilter("ignore")


class MassSpringDamper(ceemx.AbstractContinuousSystem):
    """m q̈ = u − k q − c q̇; x = (q, q̇); y = q (docs/custom_systems.md)."""

    k: Array = ceemx.param(positive=True)
    c: Array = ceemx.param(positive=True)
    m: Array = ceemx.param(fixed=True, default=1.0)

    @property
    def state_dim(self) -> int:
        """N = 2."""
        return 2

    @property
    def obs_dim(self) -> int:
        """M = 1."""
        return 1

    @property
    def control_dim(self) -> int:
        """One force."""
        return 1

    def vector_field(self, x, u, t):
        """(q̇, (u − k q − c q̇)/m)."""
        q, v = x[0], x[1]
        return jnp.stack([v, (u[0] - self.k * q - self.c * v) / self.m])

    def observe(self, x, u, t):
        """The position."""
        return x[:1]


def msd_data(B: int = 2, T: int = 40):
    """A guess and B simulated records of the mass–spring–damper."""
    prior = ceemx.GaussianPrior(jnp.zeros(2), ceemx.DiagonalGaussian(jnp.asarray(1.0), 2))
    opts = dict(dt=0.1, hold="foh", substeps=2, initial_prior=prior)
    true = MassSpringDamper(k=4.0, c=0.5, process_noise=1e-2, obs_noise=0.05, **opts)
    u = foh_inputs(jax.random.normal(jax.random.PRNGKey(0), (B, T, 1)))
    _, data = ceemx.simulate(true, jax.random.PRNGKey(1), jnp.zeros((B, 2)), T, u)
    guess = MassSpringDamper(k=3.0, c=1.0, process_noise=2e-2, obs_noise=0.1, **opts)
    return guess, data


def linear_data(B: int = 2, T: int = 30):
    """A LinearSystem guess (full noise covariances, a prior) and data with a missing value."""
    rng = np.random.default_rng(0)
    A = np.array([[0.9, 0.2], [-0.15, 0.8]])
    C = np.array([[1.0, 0.3], [0.2, 1.0]])
    y = np.zeros((B, T, 2))
    for b in range(B):
        x = rng.normal(size=2)
        for t in range(T):
            y[b, t] = C @ x + 0.3 * rng.normal(size=2)
            x = A @ x + 0.2 * rng.normal(size=2)
    mask = np.ones_like(y, dtype=bool)
    mask[:, 5, 0] = False  # a missing component: the filled second moment of Laplace EM
    data = ceemx.Trajectories(jnp.asarray(y), mask=jnp.asarray(mask))
    prior = ceemx.GaussianPrior(jnp.zeros(2), ceemx.CholeskyGaussian(cov=jnp.eye(2)))
    guess = LinearSystem(
        jnp.array([[0.7, 0.0], [0.0, 0.6]]),
        jnp.array([[0.8, 0.0], [0.1, 1.2]]),
        process_noise=ceemx.CholeskyGaussian(cov=0.2 * jnp.eye(2)),
        obs_noise=ceemx.CholeskyGaussian(cov=0.5 * jnp.eye(2)),
        initial_prior=prior,
    )
    return guess, data


def laplace_programs() -> None:
    """Laplace EM fits (learned noise: diagonal, full with a missing value) and covariances."""
    guess, data = msd_data()
    r = ceemx.fit(
        guess,
        data,
        solver=ceemx.LaplaceEM(),
        max_epochs=2,
        trainable=lambda s: (s.k, s.c, s.process_noise, s.obs_noise),
    )
    r.covariance()
    lin, ldata = linear_data()
    ceemx.fit(
        lin,
        ldata,
        solver=ceemx.LaplaceEM(acceleration=None),
        max_epochs=2,
        trainable=lambda s: (s.A, s.C, s.process_noise, s.obs_noise),
    )


def other_programs() -> None:
    """Every other solver, smoother, filter, learner and evaluation entry point."""
    guess, data = msd_data()
    for solver in (
        ceemx.Alternating(),
        ceemx.Alternating(learner=ceemx.LBFGSLearner()),
        ceemx.JointLM(),
    ):
        r = ceemx.fit(guess, data, solver=solver, max_epochs=2)
        r.covariance()
    ceemx.fit(guess, data, solver=ceemx.ParticleEM(n_particles=20, n_smoothed=4), max_epochs=2)
    lin, ldata = linear_data()
    ceemx.fit(lin, ldata, solver=ceemx.JointLM(), max_epochs=2)
    x0 = jnp.zeros(data.y.shape[:2] + (2,))
    ceemx.smooth(guess, data, x0, covariance=True)
    ceemx.ekf(guess, data)
    ceemx.ekf(lin, ldata)
    pf = ceemx.particle_filter(guess, data, n_particles=20)
    ceemx.ffbsi(guess, data, pf, n_samples=4)
    pf = ceemx.particle_filter(lin, ldata, n_particles=20, proposal="adapted")
    ceemx.ffbsi(lin, ldata, pf, n_samples=4)
    ceemx.learn(guess, x0, data, ceemx.LMLearner())
    ceemx.learn(guess, x0, data, ceemx.LBFGSLearner())
    ceemx.free_run(guess, jnp.zeros((2, 2)), data.u)
    ceemx.estimate_initial_state(guess, data, 10)
    ceemx.estimate_initial_state(guess, data, 10, warm_process_noise=(1.0, None))
    ceemx.predict_k_step(guess, data, 3)
    ceemx.predict_k_step(lin, ldata, 2)


def large_block_programs() -> None:
    """Blocks above ``lib.dense.UNROLL_MAX``: LAPACK factorisations and triangular solves per step.

    n = 9 (the smoother's eager form, a joint fit with the inverted blocks) and n = 48 (the
    smoother judging trial points by value, its covariances linearised after the loop).
    """
    for K in (3, 16):
        keys = jax.random.split(jax.random.PRNGKey(K), 4)
        true = CoupledLorenz(
            jnp.full(K, 10.0),
            jnp.full(K, 28.0),
            jnp.full(K, 8.0 / 3.0),
            random_observation_matrix(keys[0], K),
            H=random_coupling(keys[1], K),
        )
        x, data = ceemx.simulate(true, keys[2], initial_states(keys[3], 2, K), 12)
        ceemx.smooth(true, data, x + 0.1, ceemx.LMSmoother(max_steps=3), covariance=True)
        if K == 3:
            ceemx.fit(true, data, x, solver=ceemx.JointLM(), max_epochs=2)


if __name__ == "__main__":
    laplace_programs()
    if "--quick" not in sys.argv[1:]:
        other_programs()
        large_block_programs()
    print("programs: done")
