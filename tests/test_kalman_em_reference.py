"""Checks of the NumPy EM reference (tests/kalman_em_reference.py) against known answers."""

import numpy as np
import pytest
from kalman_em_reference import (
    e_step,
    em_step,
    expected_complete_loglik,
    kalman_em,
    kalman_smoother,
    m_step,
)


def _random_spd(rng, k, scale=1.0):
    M = rng.standard_normal((k, k))
    return scale * (M @ M.T / k + 0.5 * np.eye(k))


def _random_stable(rng, n, radius=0.9):
    M = rng.standard_normal((n, n))
    return radius * M / np.max(np.abs(np.linalg.eigvals(M)))


def _simulate(rng, A, C, Q, R, mu0, P0, B, T):
    n, m = A.shape[0], C.shape[0]
    y = np.zeros((B, T, m))
    for b in range(B):
        x = rng.multivariate_normal(mu0, P0)
        for t in range(T):
            y[b, t] = C @ x + rng.multivariate_normal(np.zeros(m), R)
            x = A @ x + rng.multivariate_normal(np.zeros(n), Q)
    return y


def _dense_joint(A, C, Q, R, mu0, P0, T):
    """Mean and covariance of stacked x_{1:T} and y_{1:T}, built densely."""
    n = A.shape[0]
    # Marginal means and covariances: mu_{t+1} = A mu_t, V_{t+1} = A V_t A^T + Q.
    mus = [np.asarray(mu0, float)]
    Vs = [np.asarray(P0, float)]
    for _ in range(T - 1):
        mus.append(A @ mus[-1])
        Vs.append(A @ Vs[-1] @ A.T + Q)
    mu_x = np.concatenate(mus)
    Sxx = np.zeros((T * n, T * n))
    for t in range(T):
        for s in range(t + 1):
            # Cov(x_t, x_s) = A^{t-s} V_s for t >= s.
            blk = np.linalg.matrix_power(A, t - s) @ Vs[s]
            Sxx[t * n : (t + 1) * n, s * n : (s + 1) * n] = blk
            Sxx[s * n : (s + 1) * n, t * n : (t + 1) * n] = blk.T
    Cbig = np.kron(np.eye(T), C)
    mu_y = Cbig @ mu_x
    Syy = Cbig @ Sxx @ Cbig.T + np.kron(np.eye(T), R)
    Sxy = Sxx @ Cbig.T
    return mu_x, Sxx, mu_y, Syy, Sxy


@pytest.fixture
def small_model():
    rng = np.random.default_rng(0)
    n, m, T = 2, 1, 6
    A = _random_stable(rng, n)
    C = rng.standard_normal((m, n))
    Q = _random_spd(rng, n, 0.5)
    R = _random_spd(rng, m, 0.3)
    mu0 = rng.standard_normal(n)
    P0 = _random_spd(rng, n)
    y = _simulate(rng, A, C, Q, R, mu0, P0, 1, T)[0]
    return y, A, C, Q, R, mu0, P0


def test_smoother_matches_dense_conditioning(small_model):
    y, A, C, Q, R, mu0, P0 = small_model
    T, n = y.shape[0], A.shape[0]
    mu_x, Sxx, mu_y, Syy, Sxy = _dense_joint(A, C, Q, R, mu0, P0, T)
    post_mean = mu_x + Sxy @ np.linalg.solve(Syy, y.reshape(-1) - mu_y)
    post_cov = Sxx - Sxy @ np.linalg.solve(Syy, Sxy.T)

    sm = kalman_smoother(y, A, C, Q, R, mu0, P0)
    assert sm["mean"].shape == (T, n)
    assert sm["cov"].shape == (T, n, n)
    assert sm["cross"].shape == (T - 1, n, n)
    np.testing.assert_allclose(sm["mean"], post_mean.reshape(T, n), rtol=0, atol=1e-10)
    for t in range(T):
        blk = post_cov[t * n : (t + 1) * n, t * n : (t + 1) * n]
        np.testing.assert_allclose(sm["cov"][t], blk, rtol=0, atol=1e-10)
    for t in range(T - 1):
        # Cov(x_{t+1}, x_t | y): row block t+1, column block t.
        blk = post_cov[(t + 1) * n : (t + 2) * n, t * n : (t + 1) * n]
        np.testing.assert_allclose(sm["cross"][t], blk, rtol=0, atol=1e-10)
        # The order matters: the transposed block is different for this model.
        assert not np.allclose(blk, blk.T, atol=1e-6)


def test_loglik_matches_dense_density(small_model):
    y, A, C, Q, R, mu0, P0 = small_model
    T = y.shape[0]
    _, _, mu_y, Syy, _ = _dense_joint(A, C, Q, R, mu0, P0, T)
    from scipy.stats import multivariate_normal  # on use: scipy.stats takes 1-2 s to import

    expected = multivariate_normal(mean=mu_y, cov=Syy).logpdf(y.reshape(-1))
    sm = kalman_smoother(y, A, C, Q, R, mu0, P0)
    assert abs(sm["loglik"] - expected) < 1e-10


@pytest.fixture
def em_problem():
    rng = np.random.default_rng(1)
    n, m, B, T = 2, 2, 3, 50
    A = _random_stable(rng, n, 0.8)
    C = rng.standard_normal((m, n))
    Q = _random_spd(rng, n, 0.3)
    R = _random_spd(rng, m, 0.2)
    mu0 = np.zeros(n)
    P0 = np.eye(n)
    y = _simulate(rng, A, C, Q, R, mu0, P0, B, T)
    # Start away from the truth.
    init = dict(
        A=_random_stable(rng, n, 0.5),
        C=rng.standard_normal((m, n)),
        Q=np.eye(n),
        R=np.eye(m),
    )
    return y, init, mu0, P0


def test_em_increases_loglik_monotonically(em_problem):
    y, init, mu0, P0 = em_problem
    hist = kalman_em(y, init["A"], init["C"], init["Q"], init["R"], mu0, P0, 20)
    assert len(hist) == 20
    lls = np.array([h["loglik"] for h in hist])
    assert np.all(np.isfinite(lls))
    diffs = np.diff(lls)
    assert np.all(diffs >= -1e-9 * np.abs(lls[1:])), diffs
    assert lls[-1] > lls[0] + 1.0

    # Bookkeeping: loglik of iteration k is at the parameters before the k-th M-step.
    total = sum(
        kalman_smoother(y[b], init["A"], init["C"], init["Q"], init["R"], mu0, P0)["loglik"]
        for b in range(y.shape[0])
    )
    assert abs(hist[0]["loglik"] - total) < 1e-9
    A1, C1, Q1, R1, ll0 = em_step(y, init["A"], init["C"], init["Q"], init["R"], mu0, P0)
    assert ll0 == hist[0]["loglik"]
    for key, val in zip("ACQR", (A1, C1, Q1, R1), strict=True):
        np.testing.assert_array_equal(hist[0][key], val)
    _, _, _, _, ll1 = em_step(y, A1, C1, Q1, R1, mu0, P0)
    assert ll1 == hist[1]["loglik"]
    for h in hist:
        np.testing.assert_array_equal(h["Q"], h["Q"].T)
        np.testing.assert_array_equal(h["R"], h["R"].T)
        assert np.all(np.linalg.eigvalsh(h["Q"]) > 0)
        assert np.all(np.linalg.eigvalsh(h["R"]) > 0)


def test_m_step_is_stationary_point_of_expected_complete_loglik(em_problem):
    y, init, mu0, P0 = em_problem
    stats = e_step(y, init["A"], init["C"], init["Q"], init["R"], mu0, P0)
    A, C, Q, R = m_step(stats)
    best = expected_complete_loglik(stats, A, C, Q, R)
    rng = np.random.default_rng(2)
    n, m = A.shape[0], C.shape[0]
    for eps in (1e-2, 1e-3):
        for _ in range(10):
            dA = eps * rng.standard_normal((n, n))
            dC = eps * rng.standard_normal((m, n))
            dQ = eps * rng.standard_normal((n, n))
            dR = eps * rng.standard_normal((m, m))
            dQ, dR = dQ + dQ.T, dR + dR.T
            assert expected_complete_loglik(stats, A + dA, C, Q, R) <= best
            assert expected_complete_loglik(stats, A, C + dC, Q, R) <= best
            assert expected_complete_loglik(stats, A, C, Q + dQ, R) <= best
            assert expected_complete_loglik(stats, A, C, Q, R + dR) <= best
            assert expected_complete_loglik(stats, A + dA, C + dC, Q + dQ, R + dR) <= best
    # Stationarity, not just a local maximum: the first-order change vanishes, so the drop
    # shrinks quadratically with the perturbation size.
    d = rng.standard_normal((n, n))
    drop1 = best - expected_complete_loglik(stats, A + 1e-2 * d, C, Q, R)
    drop2 = best - expected_complete_loglik(stats, A + 1e-3 * d, C, Q, R)
    assert drop1 > 0 and drop2 > 0
    assert drop1 / drop2 == pytest.approx(100.0, rel=1e-3)
