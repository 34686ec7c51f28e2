"""Tests for the extended Kalman filter (ceemx.inference.ekf.ekf).

Oracles: a textbook Kalman filter in NumPy (inputs, full noise covariances, missing components
and steps skipped) and the dense joint Gaussian density of all observations of a linear-Gaussian
model. The linear problems share one shape (B = 2, T = 7, n = 2, m = 3, p = 2), so the filter
compiles once for them.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, ArrayLike, Float, Real

import ceemx
from ceemx.inference.ekf import FilterSolution, ekf
from ceemx.lib.results import codes
from ceemx.models.noise import AbstractNoise, CholeskyGaussian, DiagonalGaussian
from ceemx.models.student_t import StudentT
from ceemx.models.system import AbstractSystem, GaussianPrior
from ceemx.systems import LinearSystem

RESULTS = ceemx.RESULTS
OK, NONFINITE = codes(RESULTS.successful), codes(RESULTS.nonfinite)

B, T, N_X, M_Y, P_U = 2, 7, 2, 3, 2
A = np.array([[0.9, 0.3], [-0.2, 0.7]])
B_IN = np.array([[0.5, -0.1], [0.2, 0.4]])
C = np.array([[1.0, 0.0], [0.4, 1.0], [-0.3, 0.6]])
D = np.array([[0.1, 0.0], [0.0, -0.2], [0.3, 0.1]])
Q = np.array([[0.3, 0.1], [0.1, 0.2]])
R = np.array([[0.5, 0.1, 0.0], [0.1, 0.4, -0.1], [0.0, -0.1, 0.3]])
M0 = np.array([0.5, -1.0])
P0 = np.array([[1.5, 0.2], [0.2, 0.8]])


def linear_system(dtype=np.float64, prior=False):
    cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    initial = GaussianPrior(cast(M0), CholeskyGaussian(cov=cast(P0))) if prior else None
    return LinearSystem(
        cast(A),
        cast(C),
        cast(B_IN),
        cast(D),
        process_noise=CholeskyGaussian(cov=cast(Q)),
        obs_noise=CholeskyGaussian(cov=cast(R)),
        initial_prior=initial,
    )


def linear_data(masked=True, seed=0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    y = rng.normal(size=(B, T, M_Y))
    u = rng.normal(size=(B, T, P_U))
    mask = np.ones((B, T, M_Y), bool)
    if masked:
        mask[0, 0] = False  # the very first step missing
        mask[0, 3, [0, 2]] = False
        mask[1, 2] = False
        mask[1, 4, 1] = False
        mask[1, 5, 0] = False
    return ceemx.Trajectories(y.astype(dtype), u.astype(dtype), mask)


def textbook_kalman(y, u, mask, m0, p0):
    """Predicted obs, innovation covariances, predicted/filtered means, filtered covariances and
    log p(y) of one trajectory (missing components skip their update)."""
    mp, mf, pf = np.zeros((T, N_X)), np.zeros((T, N_X)), np.zeros((T, N_X, N_X))
    yh, S = np.zeros((T, M_Y)), np.zeros((T, M_Y, M_Y))
    ll = 0.0
    m_prev, P = m0, p0
    for t in range(T):
        if t > 0:
            m_prev = A @ mf[t - 1] + B_IN @ u[t - 1]
            P = A @ pf[t - 1] @ A.T + Q
        mp[t] = m_prev
        yh[t] = C @ m_prev + D @ u[t]
        S[t] = C @ P @ C.T + R
        o = mask[t]
        if not o.any():
            mf[t], pf[t] = m_prev, P
            continue
        S_o = S[t][np.ix_(o, o)]
        K = P @ C[o].T @ np.linalg.inv(S_o)
        r = y[t, o] - yh[t, o]
        mf[t] = m_prev + K @ r
        pf[t] = P - K @ C[o] @ P
        _, logdet = np.linalg.slogdet(S_o)
        ll += -0.5 * (r @ np.linalg.solve(S_o, r) + logdet + o.sum() * math.log(2 * math.pi))
    return yh, S, mp, mf, pf, ll


def dense_log_density(y, u, m0, p0):
    """log N(vec y; mean, cov) of one unmasked trajectory, from the stacked linear map
    x = Φ ξ + c with ξ = (x₁ − m₀, w₁, …, w_{T−1})."""
    Phi = np.zeros((T * N_X, T * N_X))
    c = np.zeros((T, N_X))
    c[0] = m0
    for t in range(1, T):
        c[t] = A @ c[t - 1] + B_IN @ u[t - 1]
    for t in range(T):
        for s in range(t + 1):
            Phi[t * N_X : (t + 1) * N_X, s * N_X : (s + 1) * N_X] = np.linalg.matrix_power(A, t - s)
    Xi = np.kron(np.eye(T), Q)
    Xi[:N_X, :N_X] = p0
    Cb = np.kron(np.eye(T), C)
    mean = (c @ C.T + u @ D.T).reshape(-1)
    cov = Cb @ Phi @ Xi @ Phi.T @ Cb.T + np.kron(np.eye(T), R)
    r = y.reshape(-1) - mean
    _, logdet = np.linalg.slogdet(cov)
    return -0.5 * (r @ np.linalg.solve(cov, r) + logdet + r.size * math.log(2 * math.pi))


def gram(L):
    L = np.asarray(L)
    return L @ np.swapaxes(L, -1, -2)


def check_against_textbook(sol, data, m0, p0):
    y, u, mask = (np.asarray(a) for a in (data.y, data.u, data.mask))
    for b in range(B):
        yh, S, mp, mf, pf, ll = textbook_kalman(y[b], u[b], mask[b], m0, p0)
        kw = dict(rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(sol.predicted_obs[b], yh, **kw)
        np.testing.assert_allclose(gram(sol.innovation_chol[b]), S, **kw)
        np.testing.assert_allclose(sol.predicted_means[b], mp, **kw)
        np.testing.assert_allclose(sol.filtered_means[b], mf, **kw)
        np.testing.assert_allclose(gram(sol.filtered_chol[b]), pf, **kw)
        np.testing.assert_allclose(sol.log_likelihood[b], ll, **kw)
    np.testing.assert_array_equal(codes(sol.status), [OK] * B)


def test_ekf_on_a_linear_model_is_the_kalman_filter():
    data = linear_data()
    # An explicit `initial` overrides the system's own prior (one compiled program for both: the
    # system's pytree and the prior's noise type are the same in the two calls).
    m1, p1 = np.array([-0.2, 0.3]), np.array([[0.6, -0.1], [-0.1, 1.1]])
    sol = ekf(
        linear_system(prior=True),
        data,
        initial=GaussianPrior(jnp.asarray(m1), CholeskyGaussian(cov=p1)),
    )
    assert isinstance(sol, FilterSolution)
    check_against_textbook(sol, data, m1, p1)
    # The system's own prior is the default ...
    check_against_textbook(ekf(linear_system(prior=True), data), data, M0, P0)
    # ... and without one, N(0, I) (the authors' evaluation).
    check_against_textbook(ekf(linear_system(), data), data, np.zeros(N_X), np.eye(N_X))
    for leaf in jax.tree_util.tree_leaves(sol):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == jnp.float64


def test_log_likelihood_is_the_dense_joint_density():
    data = linear_data(masked=False, seed=1)
    sol = ekf(linear_system(prior=True), data)
    y, u = np.asarray(data.y), np.asarray(data.u)
    want = [dense_log_density(y[b], u[b], M0, P0) for b in range(B)]
    np.testing.assert_allclose(sol.log_likelihood, want, rtol=1e-10, atol=1e-10)


def test_predictions_are_made_before_the_correction():
    data = linear_data()
    system = linear_system(prior=True)
    base = np.asarray(ekf(system, data).predicted_obs)
    b, t0 = 1, 3  # an observed step of trajectory 1
    y = np.asarray(data.y).copy()
    y[b, t0] += 5.0
    pert = np.asarray(ekf(system, ceemx.Trajectories(y, data.u, data.mask)).predicted_obs)
    np.testing.assert_array_equal(pert[b, : t0 + 1], base[b, : t0 + 1])  # y_t never predicts y_t
    assert np.all(np.abs(pert[b, t0 + 1 :] - base[b, t0 + 1 :]).max(axis=-1) > 1e-8)
    np.testing.assert_array_equal(pert[1 - b], base[1 - b])  # trajectories are independent


class Pendulum(AbstractSystem):
    """A small nonlinear system with a time-dependent forcing and a nonlinear observation:
    x_{t+1} = (x₀ + h x₁, x₁ + h(−a sin x₀ + u + 0.3 sin(0.5 t))), y = (sin x₀ + ½x₁, x₀ x₁)."""

    a: Float[Array, ""]
    process_noise: AbstractNoise
    obs_noise: AbstractNoise
    initial_prior: GaussianPrior | None

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 2

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t: Real[ArrayLike, ""]):
        h = 0.1
        force = -self.a * jnp.sin(x[0]) + u[0] + 0.3 * jnp.sin(0.5 * jnp.asarray(t, x.dtype))
        return jnp.stack([x[0] + h * x[1], x[1] + h * force])

    def observe(self, x, u, t: Real[ArrayLike, ""]):
        return jnp.stack([jnp.sin(x[0]) + 0.5 * x[1], x[0] * x[1]])


def pendulum(q_scale, r_scale):
    return Pendulum(
        a=jnp.asarray(1.2),
        process_noise=DiagonalGaussian(q_scale, 2),
        obs_noise=DiagonalGaussian(r_scale, 2),
        initial_prior=None,
    )


@pytest.mark.slow
def test_nonlinear_batch_equals_single_trajectories_and_isolates_failures():
    system = pendulum(0.05, 0.1)
    x0 = jnp.array([[0.5, 0.0], [-0.3, 0.4], [1.0, -0.5]])
    u = 0.2 * jax.random.normal(jax.random.PRNGKey(1), (3, T, 1))
    _, data = ceemx.simulate(system, jax.random.PRNGKey(0), x0, T, u)
    u_bad = np.asarray(data.u).copy()
    u_bad[1, 3, 0] = 1e200  # trajectory 1 blows up after step 3
    mask = np.ones((3, T, 2), bool)
    mask[0, 2, 1] = mask[2, 4] = False
    data = ceemx.Trajectories(data.y, u_bad, mask)
    sol = ekf(system, data)
    np.testing.assert_array_equal(codes(sol.status), [OK, NONFINITE, OK])
    for b in range(3):
        single = ekf(system, data[b])
        for got, want in zip(
            jax.tree_util.tree_leaves(sol), jax.tree_util.tree_leaves(single), strict=True
        ):
            np.testing.assert_allclose(got[b], want[0], rtol=1e-12, atol=1e-12)
    # The failed trajectory: finite up to its failure, NaN everywhere from then on.
    bad = np.isnan(np.asarray(sol.predicted_means[1])).any(axis=-1)
    first = int(np.argmax(bad))
    assert 3 < first and bad[first:].all() and not bad[:first].any()
    for arr in (sol.predicted_obs, sol.innovation_chol, sol.filtered_means, sol.filtered_chol):
        a = np.asarray(arr[1]).reshape(T, -1)
        assert np.isnan(a[first:]).all() and np.isfinite(a[:first]).all()
    assert np.isnan(sol.log_likelihood[1])
    assert np.isfinite(np.asarray(sol.log_likelihood)[[0, 2]]).all()


def test_ekf_with_tiny_noise_and_exact_start_tracks_the_truth():
    system = pendulum(1e-8, 1e-6)
    x0 = jnp.array([[0.5, 0.0], [-0.3, 0.4], [1.0, -0.5]])
    u = 0.2 * jax.random.normal(jax.random.PRNGKey(1), (3, T, 1))
    xs, data = ceemx.simulate(
        system, jax.random.PRNGKey(0), x0, T, u, process_noise=False, obs_noise=False
    )
    sols = [
        ekf(system, data[b], initial=GaussianPrior(x0[b], DiagonalGaussian(1e-8, 2)))
        for b in range(3)
    ]
    for b, sol in enumerate(sols):
        np.testing.assert_allclose(sol.filtered_means[0], xs[b], atol=1e-6)
        np.testing.assert_allclose(sol.predicted_means[0], xs[b], atol=1e-6)
        np.testing.assert_allclose(sol.predicted_obs[0], data.y[b], atol=1e-6)


def test_bad_inputs_raise_naming_the_argument():
    system = linear_system()
    data = linear_data()
    with pytest.raises(TypeError, match="system.obs_noise"):
        ekf(LinearSystem(A, C, B_IN, D, obs_noise=StudentT(1.0, 4.0, M_Y)), data)
    with pytest.raises(TypeError, match="system.process_noise"):
        ekf(LinearSystem(A, C, B_IN, D, process_noise=StudentT(1.0, 4.0, N_X)), data)
    with pytest.raises(TypeError, match="initial.noise"):
        ekf(system, data, initial=GaussianPrior(jnp.zeros(N_X), StudentT(1.0, 4.0, N_X)))
    with pytest.raises(ValueError, match="initial.mean"):
        ekf(system, data, initial=GaussianPrior(jnp.zeros(3), DiagonalGaussian(1.0, 3)))
    with pytest.raises(ValueError, match="system.obs_noise"):
        ekf(LinearSystem(A, C, B_IN, D, obs_noise=DiagonalGaussian(1.0, 2)), data)
    with pytest.raises(TypeError, match="data"):
        ekf(system, np.asarray(data.y))
    with pytest.raises(TypeError, match="system"):
        ekf("not a system", data)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="data.y"):
        ekf(system, ceemx.Trajectories(rng.normal(size=(B, T, 2)), data.u))
    with pytest.raises(ValueError, match="data.u"):
        ekf(system, ceemx.Trajectories(data.y, rng.normal(size=(B, T, 1))))
    # float32 data are promoted to the system's float64, as by fit and smooth
    assert ekf(system, linear_data(dtype=np.float32)).predicted_obs.dtype == jnp.float64


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_in_is_dtype_out(dtype):
    sol = ekf(linear_system(dtype, prior=True), linear_data(dtype=dtype))
    for leaf in jax.tree_util.tree_leaves(sol):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == dtype
    ref = ekf(linear_system(prior=True), linear_data())
    tol = 1e-4 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(sol.predicted_obs, ref.predicted_obs, rtol=tol, atol=tol)
    np.testing.assert_allclose(sol.log_likelihood, ref.log_likelihood, rtol=tol)
