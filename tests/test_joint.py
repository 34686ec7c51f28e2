"""The joint (x, θ) Levenberg–Marquardt method: exact steps, agreement with alternation, failure paths."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx import lib as linalg
from ceemx.learning import make_problem
from ceemx.lib import marquardt_scale
from ceemx.lib.results import codes
from ceemx.objective import linearize
from ceemx.systems import CoupledLorenz, initial_states, random_coupling, random_observation_matrix

LORENZ_PARAMS = lambda s: (s.sigma, s.rho, s.beta, s.H)  # noqa: E731


def _coupled(K=2, T=6, B=2, seed=0, pn=0.3, on=0.1):
    k1, k2, k3, k4, k5 = jax.random.split(jax.random.PRNGKey(seed), 5)
    H = random_coupling(k1, K)
    C = random_observation_matrix(k2, K)
    system = CoupledLorenz(
        jnp.full(K, 10.0),
        jnp.full(K, 28.0),
        jnp.full(K, 8 / 3),
        C,
        H=H,
        process_noise=pn,
        obs_noise=on,
    )
    xs, data = ceemx.simulate(system, k4, initial_states(k3, B, K), T)
    x = xs + 0.1 * jax.random.normal(k5, xs.shape)
    return system, data, x, xs


def test_joint_step_equals_dense_gauss_newton():
    """The arrowhead solve of the damped joint normal equations equals a dense NumPy solve."""
    system, data, x, _ = _coupled()
    problem, th = make_problem(system, x, data, trainable=LORENZ_PARAMS)
    B, T, n = x.shape

    def r(xflat, th):
        return ceemx.whitened_residuals(problem.build(th), xflat.reshape(x.shape), data).reshape(-1)

    Jx = np.asarray(jax.jacfwd(r, 0)(x.reshape(-1), th))
    Jt = np.asarray(jax.jacfwd(r, 1)(x.reshape(-1), th))
    rv = np.asarray(r(x.reshape(-1), th))
    lam = 1e-3
    lin = jax.vmap(lambda xb, y, u, m: linearize(problem.build, th, xb, y, u, m, wrt_theta=True))(
        x, data.y, data.u, data.mask
    )
    # Same damping on both sides: Marquardt scaling per variable.
    A = lin.hess_x
    dA = jnp.diagonal(A.diagonal, axis1=-2, axis2=-1)
    sA = marquardt_scale(dA.reshape(-1), lam).reshape(dA.shape)
    D = lin.D.sum(0)
    sD = marquardt_scale(jnp.diag(D), lam)
    A_d = linalg.add_to_diagonal(A, sA)
    sol = linalg.arrowhead_solve(A_d, lin.E, D + jnp.diag(sD), -lin.grad_x, -lin.grad_theta.sum(0))
    H = np.block([[Jx.T @ Jx, Jx.T @ Jt], [Jt.T @ Jx, Jt.T @ Jt]])
    g = np.concatenate([Jx.T @ rv, Jt.T @ rv])
    step = -np.linalg.solve(H + np.diag(np.concatenate([np.ravel(sA), np.asarray(sD)])), g)
    assert bool(sol.ok)
    np.testing.assert_allclose(
        np.ravel(sol.dx), step[: B * T * n], rtol=1e-9, atol=1e-9 * np.abs(step).max()
    )
    np.testing.assert_allclose(
        sol.dtheta, step[B * T * n :], rtol=1e-9, atol=1e-9 * np.abs(step).max()
    )


def _single_lorenz(B=2, T=64, seed=3, sigma_w=0.01, sigma_v=0.05, C=None):
    k1, k2, k3, k4 = jax.random.split(jax.random.PRNGKey(seed), 4)
    C = random_observation_matrix(k1, 1) if C is None else C
    true = CoupledLorenz(10.0, 28.0, 8 / 3, C, process_noise=sigma_w, obs_noise=sigma_v)
    xs, data = ceemx.simulate(true, k2, initial_states(k3, B, 1), T)
    guess = CoupledLorenz(10.6, 27.0, 2.5, C, process_noise=sigma_w, obs_noise=sigma_v)
    return true, guess, data, xs


def test_joint_and_alternate_reach_the_same_optimum():
    # Fully observed with process noise dominating: x and θ weakly coupled, so that alternation
    # (which crawls on strongly coupled problems) also converges in a few hundred epochs.
    true, guess, data, xs = _single_lorenz(sigma_w=0.1, sigma_v=0.01, C=jnp.eye(3))
    x0 = xs + 0.05 * jax.random.normal(jax.random.PRNGKey(9), xs.shape)
    tr = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731
    joint = ceemx.fit(guess, data, x0, solver=ceemx.JointLM(rtol=1e-13), trainable=tr, max_epochs=40)
    alt = ceemx.fit(
        guess,
        data,
        x0,
        solver=ceemx.Alternating(smoother=ceemx.LMSmoother(rtol=1e-14), rtol=1e-13),
        trainable=tr,
        max_epochs=400,
    )
    assert joint.converged
    assert alt.converged
    th = lambda s: np.array([s.sigma[0], s.rho[0], s.beta[0]])  # noqa: E731
    np.testing.assert_allclose(th(joint.system), th(alt.system), rtol=1e-6)
    np.testing.assert_allclose(joint.states, alt.states, atol=1e-5)
    # J never decreases across accepted joint steps.
    J = joint.history_array("J")
    assert np.all(np.diff(J) >= -1e-9 * np.abs(J[1:]))
    assert J[0] >= joint.initial_J


def test_matrix_free_cg_matches_dense_schur():
    true, guess, data, xs = _single_lorenz(B=2, T=32)
    x0 = xs + 0.05 * jax.random.normal(jax.random.PRNGKey(1), xs.shape)
    tr = lambda s: (s.sigma, s.rho, s.beta, s.C)  # noqa: E731  # p = 9
    kw = dict(trainable=tr, max_epochs=30)
    dense = ceemx.fit(guess, data, x0, solver=ceemx.JointLM(linear_solver="dense", rtol=1e-14), **kw)
    cg = ceemx.fit(
        guess, data, x0, solver=ceemx.JointLM(linear_solver="cg", cg_rtol=1e-13, rtol=1e-14), **kw
    )
    flat = lambda s: np.concatenate([np.ravel(a) for a in (s.sigma, s.rho, s.beta, s.C)])  # noqa: E731
    np.testing.assert_allclose(flat(cg.system), flat(dense.system), rtol=1e-6)


def test_joint_excludes_nonfinite_trajectory_with_status():
    true, guess, data, xs = _single_lorenz(B=3, T=32)
    x0 = xs.at[1].set(1e200)
    tr = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731
    with pytest.warns(UserWarning, match="excluded"):
        res = ceemx.fit(guess, data, x0, solver=ceemx.JointLM(), trainable=tr, max_epochs=30)
    status = codes(res.status)
    assert status[1] == codes(ceemx.RESULTS.nonfinite)
    assert np.all(status[[0, 2]] == codes(ceemx.RESULTS.successful))
    assert np.all(np.isfinite(np.asarray(res.system.sigma)))
    ref = ceemx.fit(
        guess,
        data[np.array([0, 2])],
        xs[np.array([0, 2])],
        solver=ceemx.JointLM(),
        trainable=tr,
        max_epochs=30,
    )
    np.testing.assert_allclose(res.system.sigma, ref.system.sigma, rtol=1e-8)


def test_joint_nonfinite_everywhere_reports_status_not_nan():
    true, guess, data, xs = _single_lorenz(B=1, T=16)
    x0 = jnp.full_like(xs, 1e200)
    with pytest.warns(UserWarning):
        res = ceemx.fit(
            guess, data, x0, solver=ceemx.JointLM(), trainable=lambda s: s.sigma, max_epochs=5
        )
    assert codes(res.status)[0] == codes(ceemx.RESULTS.nonfinite)
    assert not res.converged
    assert np.all(np.isfinite(np.asarray(res.system.sigma)))


def test_singular_schur_complement_is_damped_not_nan():
    """A parameter with no effect makes S singular; the step stays finite and the fit converges."""
    true, guess, data, xs = _single_lorenz(B=1, T=32)
    # H of a single attractor is masked out entirely: 9 parameters with zero Jacobian columns.
    res = ceemx.fit(
        guess, data, xs, solver=ceemx.JointLM(), trainable=lambda s: (s.sigma, s.H), max_epochs=30
    )
    assert res.converged
    assert np.all(np.isfinite(np.asarray(res.system.H)))
    np.testing.assert_allclose(res.system.H, guess.H)  # no gradient, no move
