"""Matrix-free Gauss–Newton for large θ: the products, the border, the learner, the joint option.

Oracles are the dense forms of the same quantities: the joint linearisation's E and D
(:func:`ceemx.inference.objective.linearize`), :func:`ceemx.lib.arrowhead_solve` on the damped
joint normal equations, :class:`ceemx.LMLearner`'s step and ``JointLM``'s dense iteration. The
problem is coupled Lorenz with K = 2 (n = 6, θ = (σ, ρ, β, H): P = 42), T = 12, B = 2. The option
checks and the memory guards run in the default suite (the guards on a problem of the same sizes
drawn in NumPy: they refuse by sizes); the border's step, the learner and the JointLM comparisons
compile two linearisations / learners / fits each and are marked slow.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx import lib
from ceemx.identification.learning import (
    gauss_newton_diagonal,
    gauss_newton_product,
    make_problem,
)
from ceemx.inference.objective import linearize
from ceemx.systems import CoupledLorenz, initial_states, random_coupling, random_observation_matrix

K, T, B = 2, 12, 2


def trainable(s):
    return (s.sigma, s.rho, s.beta, s.H)


@pytest.fixture(scope="module")
def setup():
    n = 3 * K
    C = random_observation_matrix(jax.random.PRNGKey(0), K, m=n - 1)
    H = random_coupling(jax.random.PRNGKey(1), K)
    true = CoupledLorenz(
        jnp.full(K, 10.0), jnp.full(K, 28.0), jnp.full(K, 8 / 3), C, H=H,
        process_noise=0.05, obs_noise=0.1,
    )  # fmt: skip
    x1 = initial_states(jax.random.PRNGKey(2), B, K)
    states, data = eqx.filter_jit(ceemx.simulate)(true, jax.random.PRNGKey(3), x1, T)
    guess = CoupledLorenz(
        jnp.full(K, 10.5), jnp.full(K, 27.0), jnp.full(K, 2.8), C, H=1.05 * H,
        process_noise=0.05, obs_noise=0.1,
    )  # fmt: skip
    x0 = states + 0.05 * jax.random.normal(jax.random.PRNGKey(4), states.shape)
    return guess, x0, data


@pytest.fixture(scope="module")
def sizes():
    """``setup``'s problem sizes with random values drawn in NumPy (no simulation to compile):
    the memory guards refuse by sizes alone."""
    n = 3 * K
    rng = np.random.default_rng(0)
    s = jnp.asarray
    H = 0.5 * rng.standard_normal((n, n)) * np.kron(1 - np.eye(K), np.ones((3, 3)))  # coupling
    C = rng.standard_normal((n - 1, n))  # a random observation matrix
    guess = CoupledLorenz(
        s(np.full(K, 10.5)), s(np.full(K, 27.0)), s(np.full(K, 2.8)), s(C),
        H=s(H), process_noise=0.05, obs_noise=0.1,
    )  # fmt: skip
    x0 = np.asarray([-6.0, -6.0, 24.0] * K) + 5.0 * rng.standard_normal((B, T, n))
    data = ceemx.Trajectories(s(x0[..., 1:] + 0.1 * rng.standard_normal((B, T, n - 1))))
    return guess, s(x0), data


@eqx.filter_jit
def _border_steps(problem, x, th, lam):
    """(dense arrowhead solution, matrix-free solution, diag(D), gauss_newton_diagonal)."""
    data = problem.data
    lin = jax.vmap(lambda xb, y, u, m: linearize(problem.build, th, xb, y, u, m, wrt_theta=True))(
        x, data.y, data.u, data.mask
    )
    A = lin.hess_x
    dA = jnp.diagonal(A.diagonal, axis1=-2, axis2=-1)
    A_d = lib.add_to_diagonal(A, lib.marquardt_scale(dA, lam))
    D = lin.D.sum(0)
    sD = lib.marquardt_scale(jnp.diag(D), lam)
    gx, gt = -lin.grad_x, -lin.grad_theta.sum(0)
    dense = lib.arrowhead_solve(A_d, lin.E, D + jnp.diag(sD), gx, gt, method="dense")
    w = jnp.ones((x.shape[0],), x.dtype)
    gn = gauss_newton_product(problem.build, th, x, data, w)
    zx = jnp.zeros_like(x)

    def border(v):
        Ev, Dv = gn(zx, v)
        return Ev, Dv + sD * v

    free = lib.arrowhead_solve_matrix_free(
        A_d,
        border,
        lambda z: gn(z, jnp.zeros_like(th))[1],
        gx,
        gt,
        preconditioner=jnp.diag(D) + sD,
        cg_rtol=1e-14,
        cg_max_steps=th.shape[0] * 4,
    )
    return dense, free, jnp.diag(D), gauss_newton_diagonal(problem.build, th, x, data, w)


@pytest.mark.slow  # compiles the dense and the matrix-free linearisations (≈ 4 s)
def test_matrix_free_border_step_equals_dense_arrowhead_solve(setup):
    """E_b v, D v, E_bᵀ w by JVPs and S by PCG give the dense Schur-complement step (1e-8)."""
    guess, x0, data = setup
    problem, th = make_problem(guess, x0, data, trainable=trainable)
    dense, free, diag_D, diag_free = _border_steps(problem.problem, x0, th, jnp.asarray(1e-3))
    assert bool(dense.ok) and bool(free.ok) and bool(free.converged)
    assert free.method == "cg-matrix-free" and 0 < int(free.cg_steps) <= 4 * th.shape[0]
    np.testing.assert_allclose(diag_free, diag_D, rtol=1e-10)
    scale = float(jnp.max(jnp.abs(dense.dtheta)))
    np.testing.assert_allclose(free.dtheta, dense.dtheta, rtol=1e-8, atol=1e-8 * scale)
    scale = float(jnp.max(jnp.abs(dense.dx)))
    np.testing.assert_allclose(free.dx, dense.dx, rtol=1e-8, atol=1e-8 * scale)


@pytest.mark.slow
@pytest.mark.parametrize("damping", [1e-2, 1.0])
def test_gauss_newton_cg_learner_step_equals_lm_learner_step(setup, damping):
    """One LM iteration with CG to convergence = LMLearner's (dense Cholesky) iteration."""
    guess, x0, data = setup
    P = 3 * K + 9 * K * K
    dense = ceemx.LMLearner(max_steps=1, damping=damping)
    free = ceemx.GaussNewtonCGLearner(
        max_steps=1, damping=damping, cg_rtol=1e-14, cg_max_steps=4 * P
    )
    s_dense, _, i_dense = ceemx.learn(guess, x0, data, dense, trainable=trainable)
    s_free, _, i_free = ceemx.learn(guess, x0, data, free, trainable=trainable)
    p0, _ = make_problem(guess, x0, data, trainable=trainable)
    th0 = p0.problem.theta_of(guess)
    th_d, th_f = p0.problem.theta_of(s_dense), p0.problem.theta_of(s_free)
    assert float(jnp.max(jnp.abs(th_d - th0))) > 1e-3  # the step was taken
    np.testing.assert_allclose(th_f, th_d, rtol=1e-8, atol=1e-8 * float(jnp.max(jnp.abs(th_d))))
    np.testing.assert_allclose(i_free.value_after, i_dense.value_after, rtol=1e-10)


def test_gauss_newton_cg_learner_checks_options_and_problem():
    with pytest.raises(ValueError, match="scaling"):
        ceemx.GaussNewtonCGLearner(scaling="exact")
    with pytest.raises(ValueError, match="cg_max_steps"):
        ceemx.GaussNewtonCGLearner(cg_max_steps=0)
    with pytest.raises(ValueError, match="border"):
        ceemx.JointLM(border="sparse")


@pytest.mark.slow
def test_joint_matrix_free_iteration_equals_dense(setup):
    """JointLM(border="matrix-free") with CG to convergence takes the dense border's steps."""
    guess, x0, data = setup
    common = dict(max_epochs=2, progress=False, trainable=trainable, outliers="keep")
    opts = dict(check_smoothing=False, check_identifiability=False, rtol=0.0)
    res_d = ceemx.fit(guess, data, x0, solver=ceemx.JointLM(**opts), **common)
    res_f = ceemx.fit(
        guess,
        data,
        x0,
        solver=ceemx.JointLM(border="matrix-free", cg_rtol=1e-14, cg_max_steps=200, **opts),
        **common,
    )
    th_d = np.concatenate([np.ravel(a) for a in trainable(res_d.system)])
    th_f = np.concatenate([np.ravel(a) for a in trainable(res_f.system)])
    np.testing.assert_allclose(th_f, th_d, rtol=1e-7)
    np.testing.assert_allclose(res_f.states, res_d.states, rtol=1e-7, atol=1e-7)
    assert [h["J"] for h in res_f.history] == pytest.approx([h["J"] for h in res_d.history])


def test_memory_guard_names_the_matrix_free_paths(sizes, monkeypatch):
    """The dense border's refusal names JointLM(border='matrix-free') and GaussNewtonCGLearner;
    the matrix-free border has its own (B·T·n²) estimate and refuses before any compute too."""
    from ceemx.infra import memory

    guess, x0, data = sizes
    monkeypatch.setattr(memory, "physical_memory", lambda: 256)
    kw = dict(trainable=trainable, max_epochs=1, progress=False)
    with pytest.raises(ValueError, match="border='matrix-free'.*GaussNewtonCGLearner"):
        ceemx.fit(guess, data, x0, solver=ceemx.JointLM(), **kw)
    with pytest.raises(ValueError, match=r"matrix-free'\)'s x-blocks.*GaussNewtonCGLearner"):
        ceemx.fit(guess, data, x0, solver=ceemx.JointLM(border="matrix-free"), **kw)
    with pytest.raises(ValueError, match="LMLearner.*GaussNewtonCGLearner"):
        ceemx.learn(guess, x0, data, ceemx.LMLearner(), trainable=trainable)
