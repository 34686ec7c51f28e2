"""LaplaceNoise, a robust observation noise added as one class in one file: its density against the
closed form, its gradients, masked components, its sampler, the L1 MAP smoothing it gives, and a
fit on data with outliers that beats the least-squares (Gaussian) fit."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import LinearConstraint, minimize

import ceemx
from ceemx.identification.analysis.noise_estimate import estimate_noise
from ceemx.identification.analysis.summary import describe_noise
from ceemx.models.laplace_noise import LaplaceNoise
from ceemx.systems import LinearSystem

B_SCALE = np.array([0.5, 2.0])
R = np.array([0.3, -1.7])


def _closed_form(r, b, mask):
    return float(np.sum(np.where(mask, np.abs(r) / b + np.log(2.0 * b), 0.0)))


@pytest.mark.parametrize("mask", [None, np.array([True, False]), np.array([False, False])])
def test_nll_is_the_closed_form(mask):
    noise = LaplaceNoise(jnp.asarray(B_SCALE), 2)
    full = np.ones(2, bool) if mask is None else mask
    m = None if mask is None else jnp.asarray(mask)
    assert float(noise.nll(jnp.asarray(R), m)) == pytest.approx(_closed_form(R, B_SCALE, full))
    shared = LaplaceNoise(jnp.asarray(0.7), 2)
    assert float(shared.nll(jnp.asarray(R))) == pytest.approx(_closed_form(R, 0.7, np.ones(2)))


def test_gradients_match_finite_differences():
    mask = jnp.asarray([True, True, False])
    r0, b0 = np.array([0.4, -1.1, 0.8]), np.array([0.5, 1.5, 2.0])

    # under jit: one program each instead of one per eager operation and call
    nll_rs = jax.jit(lambda r, s: LaplaceNoise(s, 3).nll(r, mask))

    def nll(r, scale):
        return float(nll_rs(jnp.asarray(r), jnp.asarray(scale)))

    grad = jax.jit(jax.grad(nll_rs, argnums=(0, 1)))
    g_r, g_b = grad(jnp.asarray(r0), jnp.asarray(b0))
    h = 1e-6
    for i in range(3):
        e = np.eye(3)[i] * h
        fd_r = (nll(r0 + e, b0) - nll(r0 - e, b0)) / (2 * h)
        fd_b = (nll(r0, b0 + e) - nll(r0, b0 - e)) / (2 * h)
        assert float(g_r[i]) == pytest.approx(fd_r, rel=1e-7, abs=1e-9)
        assert float(g_b[i]) == pytest.approx(fd_b, rel=1e-7, abs=1e-9)
    # closed forms: sign(r)/b, 1/b − |r|/b²; nothing from the masked component
    np.testing.assert_allclose(g_r, [1 / 0.5, -1 / 1.5, 0.0])
    np.testing.assert_allclose(g_b, [1 / 0.5 - 0.4 / 0.25, 1 / 1.5 - 1.1 / 1.5**2, 0.0])


def test_curvature_is_the_irls_weight_and_masked_rows_are_zero():
    noise = LaplaceNoise(jnp.asarray(B_SCALE), 2)
    r = jnp.asarray(R)
    s = noise.sqrt_curvature_diagonal(r)
    # W r = ∇nll: each step minimises the quadratic that majorises |r|/b at r (to the floor)
    np.testing.assert_allclose(s**2 * r, jax.grad(noise.nll)(r), rtol=1e-12)
    np.testing.assert_array_equal(noise.sqrt_curvature(r), np.diag(s))
    masked = noise.sqrt_curvature(r, jnp.asarray([False, True]))
    np.testing.assert_array_equal(masked[0], 0.0)
    # finite at a zero residual: bounded by the floor √ε·b (ε the dtype's resolution)
    at_zero = noise.sqrt_curvature_diagonal(jnp.zeros(2))
    floor = np.sqrt(np.finfo(np.float64).eps) * B_SCALE
    np.testing.assert_allclose(at_zero**2, 1.0 / (floor * B_SCALE))


def test_masked_components_contribute_nothing():
    noise = LaplaceNoise(jnp.asarray([0.5, 2.0, 1.0]), 3)
    mask = jnp.asarray([True, False, True])
    a = noise.nll(jnp.asarray([0.3, 5.0, -0.2]), mask)
    b = noise.nll(jnp.asarray([0.3, -9.0, -0.2]), mask)
    sub = LaplaceNoise(jnp.asarray([0.5, 1.0]), 2).nll(jnp.asarray([0.3, -0.2]))
    assert float(a) == float(b) == pytest.approx(float(sub))


def test_sampling_moments():
    n = 200_000
    b = np.array([0.5, 2.0])
    draws = np.asarray(
        LaplaceNoise(jnp.asarray(b), 2).sample(jax.random.PRNGKey(0), (n,), jnp.float64)
    )
    assert draws.shape == (n, 2)
    # standard errors from the Laplace moments: Var r = 2b², Var |r| = b², Var r² = 20b⁴
    se_mean, se_abs, se_sq = np.sqrt(2) * b, b, np.sqrt(20) * b**2
    z = 5.0 / np.sqrt(n)
    assert np.all(np.abs(draws.mean(0)) < z * se_mean)
    assert np.all(np.abs(np.abs(draws).mean(0) - b) < z * se_abs)
    assert np.all(np.abs((draws**2).mean(0) - 2 * b**2) < z * se_sq)
    tail = (np.abs(draws) > 3 * b).mean(0)  # P(|r| > 3b) = e⁻³
    assert np.all(np.abs(tail - np.exp(-3)) < 5 * np.sqrt(np.exp(-3) / n))


A = np.array([[0.95, 0.1], [-0.1, 0.9]])
C = np.array([[1.0, 0.0], [0.3, 1.0]])
Q_STD = 0.1


def test_smoothing_reaches_the_l1_map():
    # Gaussian dynamics, Laplace observations: the MAP is a convex problem, a quadratic plus an L1
    # norm, solved here independently as a smooth constrained one (an interior-point method).
    T, b = 15, np.array([0.2, 0.05])
    obs_noise = LaplaceNoise(jnp.asarray(b), 2)
    system = LinearSystem(jnp.asarray(A), jnp.asarray(C), process_noise=Q_STD, obs_noise=obs_noise)
    x, data = ceemx.simulate(system, jax.random.PRNGKey(1), jnp.zeros((1, 2)), T)
    mask = np.ones((1, T, 2), bool)
    mask[0, 4:9, 1] = False
    data = ceemx.Trajectories(data.y, mask=jnp.asarray(mask))
    solver = ceemx.LMSmoother(rtol=1e-14, max_steps=500)
    sol = ceemx.smooth(system, data, jnp.zeros_like(x), solver)
    assert np.all(np.asarray(sol.converged)), sol.messages()

    # z = (x, t): ½‖D x‖²/q² + Σ t_i/b_i subject to t ≥ ±(y − G x) on the present entries
    y, present = np.asarray(data.y[0]).ravel(), mask[0].ravel()
    G = np.kron(np.eye(T), C)[present]
    D = np.kron(np.eye(T, k=1)[:-1], np.eye(2)) - np.kron(np.eye(T)[:-1], A)
    H = D.T @ D / Q_STD**2
    c = np.tile(1.0 / b, T)[present]
    k, nx = int(present.sum()), 2 * T
    yp, eye = y[present], np.eye(k)
    hess = np.zeros((nx + k, nx + k))
    hess[:nx, :nx] = H
    ref = minimize(
        lambda z: 0.5 * z[:nx] @ H @ z[:nx] + c @ z[nx:],
        np.concatenate([np.zeros(nx), np.abs(yp) + 1.0]),
        jac=lambda z: np.concatenate([H @ z[:nx], c]),
        hess=lambda z: hess,
        constraints=[
            LinearConstraint(np.block([[G, eye], [-G, eye]]), np.concatenate([yp, -yp]), np.inf)
        ],
        method="trust-constr",
        options={"gtol": 1e-12, "xtol": 1e-14, "maxiter": 5000},
    )
    assert ref.success, ref.message
    x_ref = jnp.asarray(ref.x[:nx].reshape(1, T, 2))

    log_joint = eqx.filter_jit(ceemx.log_joint)  # one program, not one per eager operation

    def f(xs):
        return float(-jnp.sum(log_joint(system, xs, data)))

    f_smooth, f_ref = f(sol.states), f(x_ref)
    dx = np.abs(np.asarray(sol.states) - np.asarray(x_ref)).max()
    print(f"L1 MAP: {f_smooth - f_ref:.1e} above the reference, max |Δx| {dx:.1e}")
    # within the floor's reach of the kinks (LaplaceNoise docs): measured 2.9e-8 and 1.1e-5
    assert f_smooth - f_ref < 1e-8 * abs(f_ref)
    assert dx < 1e-4


@pytest.mark.slow  # two end-to-end fits; the L1 MAP itself: test_smoothing_reaches_the_l1_map
def test_robust_fit_beats_a_gaussian_fit_on_data_with_outliers():
    # x' = a x + b u + w, y = x + v, one in ten observations off by ±3 (30 σ_v)
    rng = np.random.default_rng(2)
    T, a, b_in, sw, sv = 60, 0.8, 1.0, 0.05, 0.1
    u = rng.standard_normal((1, T, 1))
    x = np.zeros((1, T))
    for t in range(T - 1):
        x[:, t + 1] = a * x[:, t] + b_in * u[:, t, 0] + sw * rng.standard_normal(1)
    y = x + sv * rng.standard_normal((1, T))
    y += (rng.random((1, T)) < 0.1) * rng.choice([-1.0, 1.0], (1, T)) * 3.0
    data = ceemx.Trajectories(jnp.asarray(y[..., None]), jnp.asarray(u))

    def fit(obs_noise):
        start = LinearSystem(
            jnp.array([[0.5]]), jnp.array([[1.0]]), jnp.array([[0.5]]), jnp.zeros((1, 1)),
            process_noise=jnp.asarray(sw), obs_noise=obs_noise,
        )  # fmt: skip
        res = ceemx.fit(
            start, data, solver=ceemx.JointLM(), trainable=lambda s: (s.A, s.B), max_epochs=10,
            diagnose=False,
        )  # fmt: skip
        error = abs(float(res.system.A[0, 0]) - a) + abs(float(res.system.B[0, 0]) - b_in)
        return error, float(np.sqrt(np.mean((np.asarray(res.states)[..., 0] - x) ** 2)))

    # the same variance: 2b² = σ_v²
    err_l1, rms_l1 = fit(LaplaceNoise(jnp.asarray(sv / np.sqrt(2)), 1))
    err_l2, rms_l2 = fit(jnp.asarray(sv))
    print(
        f"A, B errors L1 {err_l1:.3f}, L2 {err_l2:.3f}; state RMS L1 {rms_l1:.3f}, L2 {rms_l2:.3f}"
    )
    # measured: A, B errors 0.020 against 0.385; state RMS 0.075 against 0.441
    assert err_l1 < 0.05 and err_l1 < 0.2 * err_l2
    assert rms_l1 < 0.25 * rms_l2  # least squares chases the outliers with the states


def test_it_is_a_noise_model_everywhere_the_library_asks():
    noise = LaplaceNoise(jnp.asarray([0.1, 0.2]), 2)
    assert describe_noise(noise) == "LaplaceNoise, scale 0.1, 0.2"
    S = np.diag([0.02, 0.08])
    np.testing.assert_allclose(noise.variance_ratios(S), [1.0, 1.0])
    np.testing.assert_allclose(noise.scaled(3.0).scale, [0.3, 0.6])
    with pytest.raises(
        ValueError, match=r"`system.obs_noise.scale` must be a scalar or have shape \(2,\)"
    ):
        LinearSystem(jnp.eye(2), jnp.eye(2), obs_noise=LaplaceNoise(jnp.ones(3), 2))
    with pytest.raises(ValueError, match="`system.obs_noise` has dimension 3"):
        LinearSystem(jnp.eye(2), jnp.eye(2), obs_noise=LaplaceNoise(0.1, 3))
    system = LinearSystem(jnp.eye(2) * 0.9, jnp.eye(2), obs_noise=noise)
    _, data = ceemx.simulate(system, jax.random.PRNGKey(0), jnp.zeros((1, 2)), 5)
    # no closed-form covariance update: learning or estimating its scale is refused by name
    with pytest.raises(ValueError, match="LaplaceNoise"):
        estimate_noise(system, data)
    with pytest.raises(ValueError, match="LaplaceNoise"):
        ceemx.fit(system, data, solver=ceemx.LaplaceEM(), trainable=lambda s: (s.A, s.obs_noise))
    with pytest.raises(ValueError, match="must be positive"):
        bad = ceemx.with_noise(system, obs_noise=LaplaceNoise(-1.0, 2))
        ceemx.smooth(bad, data, jnp.zeros((1, 5, 2)))
