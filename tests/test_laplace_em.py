"""Laplace (MAP-) EM: exact EM on linear-Gaussian models, cubature against Monte Carlo, noise."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from kalman_em_reference import kalman_em, kalman_smoother

import ceemx
from ceemx.learning import expected_learning_problem
from ceemx.lib.blocktri import cholesky, to_dense

jax.config.update("jax_enable_x64", True)


def _lg_problem(seed=0, B=3, T=40, n=2, m=2):
    rng = np.random.default_rng(seed)
    A = np.array([[0.9, 0.2], [-0.15, 0.8]])
    C = np.array([[1.0, 0.3], [0.2, 1.0]])
    Q = np.array([[0.05, 0.01], [0.01, 0.04]])
    R = np.array([[0.1, 0.02], [0.02, 0.2]])
    mu0, P0 = np.zeros(n), np.eye(n)
    y = np.zeros((B, T, m))
    for b in range(B):
        x = rng.multivariate_normal(mu0, P0)
        for t in range(T):
            y[b, t] = C @ x + rng.multivariate_normal(np.zeros(m), R)
            x = A @ x + rng.multivariate_normal(np.zeros(n), Q)
    return y, (A, C, Q, R, mu0, P0)


def _guess(n=2, m=2):
    A0 = np.array([[0.7, 0.0], [0.0, 0.6]])
    C0 = np.array([[0.8, 0.0], [0.1, 1.2]])
    Q0, R0 = 0.2 * np.eye(n), 0.5 * np.eye(m)
    return A0, C0, Q0, R0


def _system(A, C, Q, R, mu0, P0):
    prior = ceemx.GaussianPrior(jnp.asarray(mu0), ceemx.CholeskyGaussian(cov=jnp.asarray(P0)))
    return ceemx.systems.LinearSystem(
        jnp.asarray(A),
        jnp.asarray(C),
        process_noise=ceemx.CholeskyGaussian(cov=jnp.asarray(Q)),
        obs_noise=ceemx.CholeskyGaussian(cov=jnp.asarray(R)),
        initial_prior=prior,
    )


def _trainable(s):
    return (s.A, s.C, s.process_noise, s.obs_noise)


def test_e_step_is_the_rts_smoother_and_evidence_the_kalman_likelihood():
    y, (A, C, Q, R, mu0, P0) = _lg_problem()
    system = _system(A, C, Q, R, mu0, P0)
    data = ceemx.Trajectories(jnp.asarray(y))
    sol = ceemx.smooth(
        system, data, jnp.zeros(y.shape[:2] + (2,)), ceemx.LMSmoother(rtol=1e-14), covariance=True
    )
    for b in range(y.shape[0]):
        ref = kalman_smoother(y[b], A, C, Q, R, mu0, P0)
        np.testing.assert_allclose(sol.states[b], ref["mean"], atol=1e-10)
        np.testing.assert_allclose(sol.covariances[b], ref["cov"], atol=1e-10)
        np.testing.assert_allclose(sol.cross_covariances[b], ref["cross"], atol=1e-10)
        T, n = y.shape[1], 2
        log_ev = -sol.objective[b] + 0.5 * T * n * np.log(2 * np.pi) - 0.5 * sol.log_det[b]
        np.testing.assert_allclose(log_ev, ref["loglik"], rtol=1e-11)


def test_laplace_em_is_exact_em_on_a_linear_gaussian_model():
    """θ and the noise covariances equal a textbook Kalman/RTS EM at every iteration (1e-8)."""
    y, (_, _, _, _, mu0, P0) = _lg_problem()
    A0, C0, Q0, R0 = _guess()
    iters = 6
    ref = kalman_em(y, A0, C0, Q0, R0, mu0, P0, iters)
    seen = []

    def record(info):
        s = info.system
        seen.append(
            (s.A, s.C, s.process_noise.covariance(), s.obs_noise.covariance(), info.record)
        )

    data = ceemx.Trajectories(jnp.asarray(y))
    result = ceemx.fit(
        _system(A0, C0, Q0, R0, mu0, P0),
        data,
        jnp.zeros(y.shape[:2] + (2,)),
        solver=ceemx.LaplaceEM(),
        trainable=_trainable,
        max_epochs=iters,
        callbacks=[record],
        outliers="keep",
    )
    assert len(seen) == iters
    for k, (A, C, Q, R, rec) in enumerate(seen):
        np.testing.assert_allclose(A, ref[k]["A"], atol=1e-8, err_msg=f"A, iteration {k + 1}")
        np.testing.assert_allclose(C, ref[k]["C"], atol=1e-8, err_msg=f"C, iteration {k + 1}")
        np.testing.assert_allclose(Q, ref[k]["Q"], atol=1e-8, err_msg=f"Q, iteration {k + 1}")
        np.testing.assert_allclose(R, ref[k]["R"], atol=1e-8, err_msg=f"R, iteration {k + 1}")
        if k + 1 < iters:  # the log-evidence at θ_k is the reference's log-likelihood at θ_k
            np.testing.assert_allclose(rec["log_evidence"], ref[k + 1]["loglik"], rtol=1e-10)
    ev = result.history_array("log_evidence")
    assert np.all(np.diff(ev) > 0)  # EM is monotone in the likelihood
    assert np.all(result.history_array("Q_gain") > -1e-8)
