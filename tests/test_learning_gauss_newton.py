"""The learner's Gauss–Newton matrix as one product of the batch's θ-Jacobian rows.

Oracle: the whitened residual vector r̃(θ) of every trajectory (``whitened_residuals``,
−J = ½‖r̃‖² + const for Gaussian noise) differentiated by ``jax.jacfwd``: the Gauss–Newton matrix is
Σ_b w_b J_bᵀJ_b and the gradient Σ_b w_b J_bᵀr̃_b. Single Lorenz (n = 3, m = 2), T = 12, B = 3 with
weights (1, 0, 2) and a non-finite excluded trajectory; random states and data (the identities
hold at any point).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.learning import gauss_newton as gn
from ceemx.identification.learning.learning_problem import make_problem
from ceemx.inference.objective import depends_on, whitened_residuals
from ceemx.systems import CoupledLorenz


def test_depends_on_follows_the_data_flow():
    def f(x, th):
        return jnp.sin(x) * 2.0 + jnp.sum(jax.jit(lambda a: a * 0.0)(th[:1]))  # a path through θ

    def g(x, th):
        return jnp.cos(x) + th.shape[0]  # shape only: no data from θ

    x, th = jnp.ones(3), jnp.ones(4)
    assert depends_on(f, 1, x, th) and depends_on(f, 0, x, th)
    assert not depends_on(g, 1, x, th) and depends_on(g, 0, x, th)


@pytest.fixture(scope="module")
def batch():
    # Everything random drawn in NumPy (eager JAX, PRNG keys included, compiles each operation).
    rng = np.random.default_rng(0)  # any system, states and data will do: the identities are exact
    s = jnp.asarray
    C = s(rng.standard_normal((2, 3)))  # a random observation matrix
    system = CoupledLorenz(s([10.5]), s([27.0]), s([2.5]), C, obs_noise=0.3, process_noise=0.2)
    x = np.asarray([-6.0, -6.0, 24.0]) + 5.0 * rng.standard_normal((3, 12, 3))
    data = ceemx.Trajectories(s(x[..., :2] + 0.3 * rng.standard_normal((3, 12, 2))))
    x[1, 4] = np.nan  # excluded below: must not spoil the sums
    return system, s(x), data, s([1.0, 0.0, 2.0])


# observation rows absent (the default suite) / present; all rows in one chunk, or chunks of 5
# of the 36 time steps (8 chunks, the last padded by 4 weight-0 steps: each chunk's product
# summed, the NaN trajectory inside chunks)
@pytest.mark.parametrize(
    "which, steps_per_chunk",
    [("dynamics", None), ("dynamics", 5), pytest.param("all", None, marks=pytest.mark.slow)],
)
def test_gauss_newton_matches_the_residual_jacobian(batch, which, steps_per_chunk, monkeypatch):
    system, states, data, w = batch
    if steps_per_chunk is not None:  # 3 transition rows of 3 parameters per step
        monkeypatch.setattr(gn, "ROWS_CHUNK_BYTES", steps_per_chunk * 3 * 3 * 8)
    trainable = (lambda s: (s.sigma, s.rho, s.beta)) if which == "dynamics" else None
    problem, theta = make_problem(system, states, data, trainable=trainable, weights=w)
    keep = np.flatnonzero(np.asarray(w) > 0)

    @eqx.filter_jit
    def both(problem, theta):
        def r(th):
            return whitened_residuals(problem.build(th), states[keep], data[keep])

        J, r_theta = jax.jacfwd(lambda th: (lambda v: (v, v))(r(th)), has_aux=True)(theta)
        return problem.gauss_newton(theta), J, r_theta, problem.value(theta)

    (value, grad, hess), J, r, v = both(problem, theta)  # J: (b, R, P)
    J, r, wk = np.asarray(J), np.asarray(r), np.asarray(w)[keep]  # the sums in NumPy
    np.testing.assert_allclose(hess, np.einsum("b,brp,brq->pq", wk, J, J), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(grad, np.einsum("b,brp,br->p", wk, J, r), rtol=1e-11)
    np.testing.assert_allclose(value, v, rtol=1e-13)
    assert theta.shape[0] == (3 if which == "dynamics" else 3 + 6 + 9)  # σ ρ β (C, H)


def test_gram_by_column_blocks_equals_the_product():
    # P = 400: 4 blocks of 100 columns, 10 block products mirrored; exactly symmetric
    R = np.random.default_rng(1).standard_normal((50, 400))
    D = np.asarray(jax.jit(gn.gram)(jnp.asarray(R)))
    np.testing.assert_allclose(D, R.T @ R, rtol=1e-12, atol=1e-11)
    np.testing.assert_array_equal(D, D.T)


def test_gauss_newton_with_an_initial_prior_equals_the_per_trajectory_linearisation(batch):
    """The chunked build's prior terms (value and gradient; the prior mean learning too) against
    the per-trajectory joint linearisation (``AbstractLearningProblem.gauss_newton``)."""
    from ceemx.identification.learning.learning_problem import AbstractLearningProblem

    system, states, data, _ = batch
    prior = ceemx.GaussianPrior(jnp.asarray([-6.0, -6.0, 24.0]), ceemx.DiagonalGaussian(2.0, 3))
    system = eqx.tree_at(lambda s: s.initial_prior, system, prior, is_leaf=lambda v: v is None)
    problem, theta = make_problem(
        system, states[jnp.asarray([0, 2])], data[jnp.asarray([0, 2])],
        trainable=lambda s: (s.sigma, s.rho, s.beta, s.initial_prior.mean),
        weights=jnp.asarray([0.5, 2.0]),
    )  # fmt: skip
    both = eqx.filter_jit(
        lambda p, t: (p.gauss_newton(t), AbstractLearningProblem.gauss_newton(p, t))
    )
    chunked, per_trajectory = both(problem, theta)
    assert theta.shape == (6,)
    for a, b in zip(chunked, per_trajectory, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(b))))
