"""Tests for the smoothing step (ceemx.smooth) and the objective it minimises.

Oracles: a textbook Kalman filter + Rauch–Tung–Striebel smoother written in NumPy below (the exact
posterior of a linear-Gaussian system), a NumPy Gaussian log-density, jax.grad and central finite
differences. Sizes are tiny except the coupled-Lorenz problem (K = 6, T = 128, B = 8), which is
compiled once per module and shared by several tests.
"""

import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.linalg import to_dense
from ceemx.objective import linearize
from ceemx.systems import (
    CoupledLorenz,
    LinearSystem,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

RESULTS = ceemx.RESULTS
SOLVER = ceemx.LMSmoother(rho_x=0.0, rtol=1e-10, max_steps=50)


# --------------------------------------------------------------------------------------------------
# Linear-Gaussian oracle: Kalman filter + RTS smoother in NumPy
# --------------------------------------------------------------------------------------------------


def kalman_rts(A, Bu, C, Du, Q, R, m0, P0, y, u, mask):
    """Smoothed means (T, n), covariances (T, n, n) and lag-one Cov(x_{t+1}, x_t) (T-1, n, n).

    x_1 ~ N(m0, P0), x_{t+1} = A x_t + Bu u_t + w_t (w ~ N(0, Q)), y_t = C x_t + Du u_t + v_t
    (v ~ N(0, R)); only the dimensions with mask[t] True are observed at step t (the update uses
    the corresponding rows of C and rows/columns of R and is skipped when none is observed).
    """
    T, n = y.shape[0], A.shape[0]
    mp = np.zeros((T, n))
    Pp = np.zeros((T, n, n))
    mf = np.zeros((T, n))
    Pf = np.zeros((T, n, n))
    for t in range(T):
        if t == 0:
            mp[t], Pp[t] = m0, P0
        else:
            mp[t] = A @ mf[t - 1] + Bu @ u[t - 1]
            Pp[t] = A @ Pf[t - 1] @ A.T + Q
        o = np.asarray(mask[t], bool)
        if o.any():
            Co, Ro = C[o], R[np.ix_(o, o)]
            resid = y[t, o] - Co @ mp[t] - Du[o] @ u[t]
            S = Co @ Pp[t] @ Co.T + Ro
            K = np.linalg.solve(S, Co @ Pp[t]).T  # P Coᵀ S⁻¹ (S symmetric)
            mf[t] = mp[t] + K @ resid
            Pf[t] = Pp[t] - K @ S @ K.T
        else:
            mf[t], Pf[t] = mp[t], Pp[t]
    ms, Ps = mf.copy(), Pf.copy()
    cross = np.zeros((T - 1, n, n))
    for t in range(T - 2, -1, -1):
        J = np.linalg.solve(Pp[t + 1], A @ Pf[t]).T  # Pf Aᵀ Pp⁻¹
        ms[t] = mf[t] + J @ (ms[t + 1] - mp[t + 1])
        Ps[t] = Pf[t] + J @ (Ps[t + 1] - Pp[t + 1]) @ J.T
        cross[t] = (J @ Ps[t + 1]).T  # Cov(x_{t+1}, x_t) = P_{t+1|T} Jᵀ
    return ms, Ps, cross


def random_spd(rng, d, scale):
    M = rng.standard_normal((d, d))
    return scale**2 * (M @ M.T / d + 0.5 * np.eye(d))


def make_linear_problem(seed, full_cov, n=3, m=2, p=1, T=25, B=2, missing=False):
    """A random stable LinearSystem with inputs, a feedthrough and a Gaussian initial prior."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))
    Bu = rng.standard_normal((n, p))
    C = rng.standard_normal((m, n))
    Du = rng.standard_normal((m, p))
    m0 = rng.standard_normal(n)
    if full_cov:
        Q, R, P0 = random_spd(rng, n, 0.3), random_spd(rng, m, 0.2), random_spd(rng, n, 1.0)
        pn, on = ceemx.CholeskyGaussian(cov=jnp.asarray(Q)), ceemx.CholeskyGaussian(cov=jnp.asarray(R))
        prior_noise = ceemx.CholeskyGaussian(cov=jnp.asarray(P0))
    else:
        q, r, p0 = (rng.uniform(0.1, 0.5, n), rng.uniform(0.1, 0.4, m), rng.uniform(0.5, 1.5, n))
        Q, R, P0 = np.diag(q**2), np.diag(r**2), np.diag(p0**2)
        pn, on = ceemx.DiagonalGaussian(jnp.asarray(q), n), ceemx.DiagonalGaussian(jnp.asarray(r), m)
        prior_noise = ceemx.DiagonalGaussian(jnp.asarray(p0), n)
    system = LinearSystem(
        jnp.asarray(A), jnp.asarray(C), jnp.asarray(Bu), jnp.asarray(Du),
        process_noise=pn, obs_noise=on,
        initial_prior=ceemx.GaussianPrior(jnp.asarray(m0), prior_noise),
    )  # fmt: skip
    u = rng.standard_normal((B, T, p))
    x1 = m0 + rng.standard_normal((B, n)) @ np.linalg.cholesky(P0).T
    xs, data = ceemx.simulate(system, jax.random.PRNGKey(seed), jnp.asarray(x1), T, jnp.asarray(u))
    y = np.asarray(data.y)
    mask = np.ones((B, T, m), bool)
    if missing:
        mask = rng.uniform(size=(B, T, m)) > 0.3  # some dimensions
        mask[:, 5:9] = False  # some whole steps
        mask[0, 15:17] = False
        y = np.where(mask, y, np.nan)
    data = ceemx.Trajectories(jnp.asarray(y), jnp.asarray(u), jnp.asarray(mask))
    oracle = dict(A=A, Bu=Bu, C=C, Du=Du, Q=Q, R=R, m0=m0, P0=P0)
    return system, data, np.asarray(xs), mask, oracle


@pytest.mark.parametrize("missing", [False, True], ids=["observed", "missing"])
@pytest.mark.parametrize("full_cov", [True, False], ids=["cholesky", "diagonal"])
def test_linear_gaussian_matches_kalman_rts(full_cov, missing):
    system, data, xs, mask, o = make_linear_problem(3 if full_cov else 4, full_cov, missing=missing)
    B, T, n = xs.shape
    x_init = jnp.zeros((B, T, n))
    sol = ceemx.smooth(system, data, x_init, SOLVER, covariance=True)
    assert np.all(np.asarray(sol.status) == RESULTS.successful), sol.messages()
    assert sol.covariances.shape == (B, T, n, n)
    assert sol.cross_covariances.shape == (B, T - 1, n, n)
    y = np.asarray(data.y)
    u = np.asarray(data.u)
    for b in range(B):
        ms, Ps, cross = kalman_rts(**o, y=y[b], u=u[b], mask=mask[b])
        np.testing.assert_allclose(sol.states[b], ms, rtol=0, atol=1e-8)
        np.testing.assert_allclose(sol.covariances[b], Ps, rtol=0, atol=1e-8)
        np.testing.assert_allclose(sol.cross_covariances[b], cross, rtol=0, atol=1e-8)
    # The reported objective is −J at the returned states.
    np.testing.assert_allclose(
        sol.objective, -ceemx.log_joint(system, sol.states, data), rtol=1e-12
    )


# --------------------------------------------------------------------------------------------------
# Coupled Lorenz, K = 6 (n = 18, m = 16), T = 128, B = 8
# --------------------------------------------------------------------------------------------------

K_LZ, B_LZ, T_LZ = 6, 8, 128


@pytest.fixture(scope="module")
def lorenz():
    keys = jax.random.split(jax.random.PRNGKey(20240601), 5)
    K = K_LZ
    H = random_coupling(keys[0], K)
    C = random_observation_matrix(keys[1], K)
    system = CoupledLorenz(
        jnp.full(K, 10.0), jnp.full(K, 28.0), jnp.full(K, 8.0 / 3.0), C, H=H,
        process_noise=0.01, obs_noise=0.01,
    )  # fmt: skip
    x1 = initial_states(keys[2], B_LZ, K)
    truth, data = ceemx.simulate(system, keys[3], x1, T_LZ, process_noise=False)
    x_init = truth + jax.random.normal(keys[4], truth.shape)
    sol = ceemx.smooth(system, data, x_init, SOLVER)
    return types.SimpleNamespace(system=system, truth=truth, data=data, x_init=x_init, sol=sol)


def rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def test_lorenz_converges_accurately(lorenz):
    sol = lorenz.sol
    assert sol.states.shape == (B_LZ, T_LZ, 3 * K_LZ)
    assert np.all(np.asarray(sol.status) == RESULTS.successful), sol.messages()
    assert np.all(np.asarray(sol.iterations) <= 30), sol.iterations
    assert np.all(np.isfinite(np.asarray(sol.objective)))
    np.testing.assert_allclose(
        sol.objective, -ceemx.log_joint(lorenz.system, sol.states, lorenz.data), rtol=1e-12
    )
    err = rms(sol.states, lorenz.truth)
    per_traj = [rms(sol.states[b], lorenz.truth[b]) for b in range(B_LZ)]
    print(f"Lorenz K=6: RMS state error {err:.2e}, per trajectory max {max(per_traj):.2e}, "
          f"iterations {np.asarray(sol.iterations).tolist()}")  # fmt: skip
    assert err < 0.01
    assert max(per_traj) < 0.01


def _objective_after(system, data, x_init, solver):
    """(objective, states, iterations) of the smoother stopped after at most k iterations, k traced.

    Runs the very per-trajectory routine that ``smooth`` vmaps, with ``max_steps`` passed as a traced
    value so that every k shares one compilation (``LMSmoother.max_steps`` is static and would
    recompile ``smooth`` for each k; :func:`test_lorenz_objective_monotone_public_api` does that).
    """
    from ceemx.smoothing.solver import _smooth_one

    @jax.jit
    def run(k, x0, y, u, mask):
        cfg = types.SimpleNamespace(
            rho_x=solver.rho_x, rtol=solver.rtol, atol=solver.atol, damping=solver.damping,
            throw=False, max_steps=k,
        )  # fmt: skip
        one = lambda *a: _smooth_one(cfg, system, *a)  # noqa: E731
        x, value, steps, _, _ = jax.vmap(one)(x0, y, u, mask)
        return value, x, steps

    return lambda k: run(jnp.asarray(k), x_init, data.y, data.u, data.mask)


def test_lorenz_objective_monotone(lorenz):
    after = _objective_after(lorenz.system, lorenz.data, lorenz.x_init, SOLVER)
    K = int(np.max(np.asarray(lorenz.sol.iterations))) + 1
    f_init = -np.asarray(ceemx.log_joint(lorenz.system, lorenz.x_init, lorenz.data))
    objs = [f_init]
    for k in range(1, K + 1):
        value, x, steps = after(k)
        objs.append(np.asarray(value))
        assert np.all(np.asarray(steps) <= k)
    objs = np.stack(objs)  # (K + 1, B)
    print("objective per iteration (trajectory 0):", objs[:, 0])
    tol = 1e-12 * np.abs(objs[:-1])
    assert np.all(objs[1:] <= objs[:-1] + tol)
    assert np.all(objs[1] < objs[0])  # the first step is accepted from this start
    # The harness reproduces `smooth` exactly once every trajectory has stopped.
    np.testing.assert_allclose(objs[-1], lorenz.sol.objective, rtol=1e-13)
    np.testing.assert_allclose(x, lorenz.sol.states, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_lorenz_objective_monotone_public_api(lorenz):
    """The same check through ``smooth`` itself (recompiles for every max_steps)."""
    K = int(np.max(np.asarray(lorenz.sol.iterations)))
    prev = -np.asarray(ceemx.log_joint(lorenz.system, lorenz.x_init, lorenz.data))
    for k in range(1, K + 1):
        sol = ceemx.smooth(
            lorenz.system, lorenz.data, lorenz.x_init, ceemx.LMSmoother(rtol=1e-10, max_steps=k)
        )
        cur = np.asarray(sol.objective)
        assert np.all(cur <= prev + 1e-12 * np.abs(prev)), (k, cur, prev)
        prev = cur
    np.testing.assert_allclose(prev, lorenz.sol.objective, rtol=1e-13)


def test_lorenz_masked_observations(lorenz):
    rng = np.random.default_rng(11)
    y = np.array(lorenz.data.y)
    B, T, m = y.shape
    mask = rng.uniform(size=(B, T, m)) >= 0.3  # 30 % of the entries missing, per dimension
    gap = slice(60, 80)  # 20 steps with no observation at all
    mask[:, gap] = False
    y[~mask] = np.nan
    data = ceemx.Trajectories(jnp.asarray(y), mask=jnp.asarray(mask))
    sol = ceemx.smooth(lorenz.system, data, lorenz.x_init, SOLVER)
    assert np.all(np.asarray(sol.status) == RESULTS.successful), sol.messages()
    assert np.all(np.asarray(sol.iterations) <= 30), sol.iterations
    err = rms(sol.states, lorenz.truth)
    err_gap = rms(sol.states[:, gap], lorenz.truth[:, gap])
    print(f"masked Lorenz: RMS error {err:.2e} (gap {err_gap:.2e}), "
          f"iterations {np.asarray(sol.iterations).tolist()}")  # fmt: skip
    assert err < 0.05
    assert err_gap < 0.05


def test_lorenz_failing_trajectory_is_isolated(lorenz):
    bad = 3
    x_init = lorenz.x_init.at[bad].set(1e200)  # RK4 overflows: the objective is inf/nan
    sol = ceemx.smooth(lorenz.system, lorenz.data, x_init, SOLVER)
    status = np.asarray(sol.status)
    assert status[bad] == RESULTS.nonfinite
    assert sol.messages()[bad] == RESULTS.nonfinite.message
    assert not bool(sol.converged[bad])
    np.testing.assert_array_equal(sol.states[bad], x_init[bad])
    assert np.all(np.isfinite(np.asarray(sol.states)))
    others = np.arange(B_LZ) != bad
    assert np.all(status[others] == RESULTS.successful)
    np.testing.assert_allclose(sol.states[others], lorenz.sol.states[others], rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.objective[others], lorenz.sol.objective[others], rtol=1e-13)
    np.testing.assert_array_equal(sol.iterations[others], lorenz.sol.iterations[others])


# --------------------------------------------------------------------------------------------------
# Student-t observation noise (small Lorenz)
# --------------------------------------------------------------------------------------------------


def _small_lorenz(obs_noise, K=2, seed=5, process_noise=0.01, **kw):
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    return CoupledLorenz(
        jnp.full(K, 10.0), jnp.full(K, 28.0), jnp.full(K, 8.0 / 3.0),
        random_observation_matrix(keys[1], K), H=random_coupling(keys[0], K),
        process_noise=process_noise, obs_noise=obs_noise, **kw,
    )  # fmt: skip


def test_student_t_observation_noise():
    K, B, T, m, s = 2, 2, 40, 4, 0.05
    system = _small_lorenz(ceemx.StudentT(s, 4.0, m), K)
    keys = jax.random.split(jax.random.PRNGKey(8), 3)
    truth, data = ceemx.simulate(system, keys[0], initial_states(keys[1], B, K), T, process_noise=False)
    x_init = truth + 0.5 * jax.random.normal(keys[2], truth.shape)
    sol = ceemx.smooth(system, data, x_init, SOLVER)
    assert np.all(np.asarray(sol.status) == RESULTS.successful), sol.messages()

    neg_j = lambda x: -jnp.sum(ceemx.log_joint(system, x, data))  # noqa: E731
    g_sol = np.asarray(jax.grad(neg_j)(sol.states))
    g_init = np.asarray(jax.grad(neg_j)(x_init))
    rel = np.linalg.norm(g_sol) / np.linalg.norm(g_init)
    print(f"Student-t: |grad| at solution {np.abs(g_sol).max():.2e} "
          f"(relative {rel:.2e}), iterations {np.asarray(sol.iterations).tolist()}, "
          f"RMS error {rms(sol.states, truth):.2e}")  # fmt: skip
    assert rel < 1e-6

    # ν → ∞: Student-t tends to the Gaussian with the same scale.
    gauss = _small_lorenz(ceemx.DiagonalGaussian(s, m), K)
    big_df = _small_lorenz(ceemx.StudentT(s, 1e10, m), K)
    sol_g = ceemx.smooth(gauss, data, x_init, SOLVER)
    sol_t = ceemx.smooth(big_df, data, x_init, SOLVER)
    assert np.all(np.asarray(sol_g.status) == RESULTS.successful)
    assert np.all(np.asarray(sol_t.status) == RESULTS.successful)
    diff = np.abs(np.asarray(sol_t.states - sol_g.states)).max()
    print(f"Student-t df=1e10 vs Gaussian: max |dx| {diff:.2e}")
    assert diff < 1e-6


# --------------------------------------------------------------------------------------------------
# Compilation: no retrace for new data or new parameter values of the same shapes
# --------------------------------------------------------------------------------------------------

_TRACES = {"observe": 0}


class _CountingLinear(LinearSystem):
    """LinearSystem whose Python ``observe`` body counts its executions (i.e. traces under jit)."""

    def observe(self, x, u, t):
        _TRACES["observe"] += 1
        return super().observe(x, u, t)


def test_no_retrace_for_new_data_or_parameters():
    rng = np.random.default_rng(0)
    n, m, B, T = 2, 3, 3, 11  # shapes used by no other test
    A = 0.5 * rng.standard_normal((n, n))
    C = rng.standard_normal((m, n))

    def problem(A, C, seed):
        system = _CountingLinear(jnp.asarray(A), jnp.asarray(C), process_noise=0.3, obs_noise=0.2)
        x1 = jnp.asarray(np.random.default_rng(seed).standard_normal((B, n)))
        _, data = ceemx.simulate(system, jax.random.PRNGKey(seed), x1, T)
        return system, data

    sys1, data1 = problem(A, C, 1)
    sys2, data2 = problem(A, C, 2)
    sys3, data3 = problem(A + 0.1, 2.0 * C, 3)  # new θ values, same structure
    x_init = jnp.zeros((B, T, n))

    _TRACES["observe"] = 0
    sol1 = ceemx.smooth(sys1, data1, x_init, SOLVER)
    first = _TRACES["observe"]
    assert first > 0  # the first call traced (and compiled) the smoother
    sol2 = ceemx.smooth(sys2, data2, x_init + 1.0, SOLVER)
    sol3 = ceemx.smooth(sys3, data3, x_init, SOLVER)
    sol4 = ceemx.smooth(sys1, data1, x_init, ceemx.LMSmoother(rtol=1e-9, damping=1e-2))
    assert _TRACES["observe"] == first, "smooth retraced for same-shape inputs"
    for sol in (sol1, sol2, sol3, sol4):
        assert np.all(np.asarray(sol.status) == RESULTS.successful)
    assert not np.allclose(sol1.states, sol2.states)


# --------------------------------------------------------------------------------------------------
# dtypes
# --------------------------------------------------------------------------------------------------


def _dtype_problem(dtype):
    rng = np.random.default_rng(21)
    n, m, B, T = 3, 2, 2, 9
    A = (0.6 * rng.standard_normal((n, n))).astype(dtype)
    C = rng.standard_normal((m, n)).astype(dtype)
    system = LinearSystem(
        jnp.asarray(A), jnp.asarray(C),
        process_noise=ceemx.DiagonalGaussian(jnp.asarray(0.3, dtype), n),
        obs_noise=ceemx.DiagonalGaussian(jnp.asarray(0.2, dtype), m),
    )  # fmt: skip
    x1 = jnp.asarray(rng.standard_normal((B, n)).astype(dtype))
    _, data = ceemx.simulate(system, jax.random.PRNGKey(0), x1, T)
    return system, data, jnp.zeros((B, T, n), dtype)


def test_float32_in_float32_out_with_warning():
    system, data, x_init = _dtype_problem(np.float32)
    assert data.y.dtype == jnp.float32
    with pytest.warns(UserWarning, match="float32"):
        sol = ceemx.smooth(system, data, x_init, SOLVER, covariance=True)
    assert sol.states.dtype == jnp.float32
    assert sol.objective.dtype == jnp.float32
    assert sol.covariances.dtype == jnp.float32
    assert sol.cross_covariances.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(sol.states)))
    # Single precision reaches the float64 answer to single-precision accuracy.
    s64, d64, x64 = _dtype_problem(np.float64)
    sol64 = ceemx.smooth(s64, d64, x64, SOLVER)
    np.testing.assert_allclose(sol.states, sol64.states, rtol=0, atol=1e-3)


def test_float64_in_float64_out_without_warning():
    system, data, x_init = _dtype_problem(np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = ceemx.smooth(system, data, x_init, SOLVER)
    assert sol.states.dtype == jnp.float64
    assert sol.objective.dtype == jnp.float64
    assert np.all(np.asarray(sol.status) == RESULTS.successful)


# --------------------------------------------------------------------------------------------------
# The objective and its derivatives
# --------------------------------------------------------------------------------------------------


def _gauss_logpdf(r, cov):
    k = r.shape[0]
    if k == 0:
        return 0.0
    _, logdet = np.linalg.slogdet(2 * np.pi * cov)
    return -0.5 * r @ np.linalg.solve(cov, r) - 0.5 * logdet


def test_log_joint_matches_numpy_gaussian_density():
    system, data, xs, mask, o = make_linear_problem(7, full_cov=True, T=6, B=2, missing=True)
    rng = np.random.default_rng(1)
    x = xs + 0.3 * rng.standard_normal(xs.shape)
    y, u = np.asarray(data.y), np.asarray(data.u)
    expected = np.zeros(x.shape[0])
    for b in range(x.shape[0]):
        tot = _gauss_logpdf(x[b, 0] - o["m0"], o["P0"])
        for t in range(x.shape[1]):
            ob = mask[b, t]
            r = y[b, t] - o["C"] @ x[b, t] - o["Du"] @ u[b, t]
            tot += _gauss_logpdf(r[ob], o["R"][np.ix_(ob, ob)])
            if t + 1 < x.shape[1]:
                tot += _gauss_logpdf(x[b, t + 1] - o["A"] @ x[b, t] - o["Bu"] @ u[b, t], o["Q"])
        expected[b] = tot
    got = np.asarray(ceemx.log_joint(system, jnp.asarray(x), data))
    assert got.shape == (x.shape[0],)
    np.testing.assert_allclose(got, expected, rtol=1e-12)

    # Whitened residuals: −J = ½‖r̃‖² + const, so differences of ½‖r̃‖² are differences of −J.
    x2 = x + 0.1 * rng.standard_normal(x.shape)
    half_sq = lambda z: 0.5 * np.sum(np.asarray(ceemx.whitened_residuals(system, jnp.asarray(z), data)) ** 2, axis=1)  # noqa: E731, E501
    got2 = np.asarray(ceemx.log_joint(system, jnp.asarray(x2), data))
    np.testing.assert_allclose(half_sq(x2) - half_sq(x), got - got2, rtol=1e-10)


def test_linearize_gradient_and_gauss_newton_on_lorenz():
    K, B, T = 2, 2, 7
    n = 3 * K
    prior = ceemx.GaussianPrior(jnp.asarray(np.tile([-6.0, -6.0, 24.0], K)), ceemx.DiagonalGaussian(2.5, n))
    Q = random_spd(np.random.default_rng(2), n, 0.3)
    system = _small_lorenz(
        ceemx.DiagonalGaussian(0.2, 4), K, seed=9, initial_prior=prior,
        process_noise=ceemx.CholeskyGaussian(cov=jnp.asarray(Q)),
    )  # fmt: skip
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    truth, data = ceemx.simulate(system, keys[0], initial_states(keys[1], B, K), T)
    mask = np.random.default_rng(3).uniform(size=(B, T, 4)) > 0.25
    data = ceemx.Trajectories(data.y, mask=jnp.asarray(mask))
    x = truth + 0.3 * jax.random.normal(keys[2], truth.shape)

    neg_j = jax.jit(lambda z: -ceemx.log_joint(system, z, data))
    ident = lambda s: s  # noqa: E731
    for b in range(B):
        lin = linearize(ident, system, x[b], data.y[b], data.u[b], data.mask[b])
        np.testing.assert_allclose(lin.value, neg_j(x)[b], rtol=1e-12)
        g_ad = jax.grad(lambda z: neg_j(x.at[b].set(z))[b])(x[b])
        np.testing.assert_allclose(lin.grad_x, g_ad, rtol=1e-10, atol=1e-10 * np.abs(g_ad).max())

        # Central finite differences of −J, every coordinate.
        h = 1e-5
        xb = np.asarray(x[b])
        fd = np.zeros_like(xb)
        for t in range(T):
            for i in range(n):
                e = np.zeros_like(xb)
                e[t, i] = h
                fp = neg_j(x.at[b].set(xb + e))[b]
                fm = neg_j(x.at[b].set(xb - e))[b]
                fd[t, i] = (fp - fm) / (2 * h)
        np.testing.assert_allclose(lin.grad_x, fd, rtol=0, atol=1e-6 * np.abs(fd).max())

        # Gaussian noise: the Gauss–Newton blocks are JᵀJ of the whitened residuals.
        jac = jax.jacfwd(
            lambda z: ceemx.whitened_residuals(system, x.at[b].set(z), data)[b]
        )(x[b]).reshape(-1, T * n)
        np.testing.assert_allclose(to_dense(lin.hess_x), jac.T @ jac, rtol=1e-10, atol=1e-10)
