"""Laplace (MAP-) EM: exact EM on linear-Gaussian models, cubature against Monte Carlo, noise."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from kalman_em_reference import kalman_smoother

import ceemx
from ceemx.identification.learning import expected_learning_problem
from ceemx.lib.blocktri import to_dense

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


def _assert_same_model(got, want, atol):
    """A and both noise covariances of two fits of the linear-Gaussian model agree to ``atol``."""
    np.testing.assert_allclose(got.system.A, want.system.A, atol=atol)
    for noise in ("process_noise", "obs_noise"):
        np.testing.assert_allclose(
            getattr(got.system, noise).covariance(),
            getattr(want.system, noise).covariance(),
            atol=atol,
        )


@pytest.mark.slow
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


@pytest.mark.slow  # a Monte Carlo check (≈ 4 s); the cubature Gauss–Newton oracle stays
def test_cubature_expectation_matches_monte_carlo_on_lorenz():
    """Q(θ) by cubature over pairwise marginals = E_q[−log p(x, y | θ)] by Monte Carlo over q.

    q is the Laplace posterior of a single noisy Lorenz trajectory (dense here: T = 12, n = 3);
    the certainty-equivalent plug-in −log p(x̂, y | θ) is off by ~18 nats, cubature by < 4 SE.
    """
    from ceemx.experiments import common
    from ceemx.identification.problem import FitProblem
    from ceemx.inference.objective import linearize, neg_log_joint_single

    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
    p = common.lorenz_problem(43, true, B=1, T=12, sigma_w=0.1, sigma_v=0.5, coupling=False)
    smoother = ceemx.LMSmoother(rtol=1e-14)
    sol = ceemx.smooth(true, p.data, p.states, smoother, covariance=True)
    x, d = sol.states[0], p.data
    problem, theta = FitProblem.create(true, d, trainable=common.LORENZ_PARAMS)

    @eqx.filter_jit  # one program: eager (op-by-op) evaluation costs seconds of dispatch
    def estimates(problem, sol, th):
        lin = linearize(lambda s: s, true, x, d.y[0], d.u[0], d.mask[0])
        chol = jnp.linalg.cholesky(jnp.linalg.inv(to_dense(lin.hess_x)))
        mp = expected_learning_problem(
            problem, theta, sol.states, sol.covariances, sol.cross_covariances, jnp.ones(1)
        )
        z = jax.random.normal(jax.random.PRNGKey(1), (40_000, x.size))
        xs = x[None] + (z @ chol.T).reshape(-1, *x.shape)
        system = problem.build(th)
        vals = jax.vmap(neg_log_joint_single, in_axes=(None, 0, None, None, None))(
            system, xs, d.y[0], d.u[0], d.mask[0]
        )
        plug = neg_log_joint_single(system, x, d.y[0], d.u[0], d.mask[0])
        return mp.per_trajectory(th)[0], vals.mean(), vals.std() / np.sqrt(vals.size), plug

    for scale in (1.0, 1.05):
        q_cub, q_mc, se, plug = map(float, estimates(problem, sol, theta * scale))
        assert abs(q_cub - q_mc) < 4 * se + 1e-3 * abs(q_mc), (scale, q_cub, q_mc, se)
        assert abs(plug - q_mc) > 100 * se  # the correction is material


@pytest.mark.slow
def test_cubature_gauss_newton_matches_autodiff():
    """The M-step's value and gradient agree with autodiff of the expected objective."""
    y, params = _lg_problem(B=1, T=6)
    system = _system(*params)
    data = ceemx.Trajectories(jnp.asarray(y))
    sol = ceemx.smooth(system, data, jnp.zeros(y.shape[:2] + (2,)), covariance=True)
    from ceemx.identification.problem import FitProblem

    problem, theta = FitProblem.create(system, data, trainable=lambda s: (s.A, s.C))
    mp = expected_learning_problem(
        problem, theta, sol.states, sol.covariances, sol.cross_covariances, jnp.ones(1)
    )
    th = theta + 0.05

    @eqx.filter_jit  # one program each: eager (op-by-op) autodiff costs seconds of dispatch
    def both(mp, th):
        autodiff = (mp.value(th), jax.grad(mp.value)(th), jax.hessian(mp.value)(th))
        return mp.gauss_newton(th), autodiff

    (value, grad, hess), (ad_value, ad_grad, ad_hess) = both(mp, th)
    np.testing.assert_allclose(value, ad_value, rtol=1e-12)
    np.testing.assert_allclose(grad, ad_grad, rtol=1e-9, atol=1e-9)
    # The model is linear in θ with Gaussian noise: Gauss–Newton is the exact Hessian.
    np.testing.assert_allclose(hess, ad_hess, rtol=1e-9, atol=1e-8)


@pytest.mark.slow  # plain EM converges in ~230 epochs (≈ 15 s); the default suite runs the next
def test_squarem_reaches_the_em_fixed_point_in_fewer_epochs():
    """C known (an identifiable model): both reach the same A, Q, R; SQUAREM in fewer epochs."""
    y, (_, C, _, _, mu0, P0) = _lg_problem(T=60)
    A0, _, Q0, R0 = _guess()
    data = ceemx.Trajectories(jnp.asarray(y))
    x0 = jnp.zeros(y.shape[:2] + (2,))
    runs = {}
    for acc in (None, "squarem"):
        runs[acc] = ceemx.fit(
            _system(A0, C, Q0, R0, mu0, P0),
            data,
            x0,
            solver=ceemx.LaplaceEM(acceleration=acc, rtol=1e-9),
            trainable=lambda s: (s.A, s.process_noise, s.obs_noise),
            max_epochs=400,
            outliers="keep",
        )
    plain, fast = runs[None], runs["squarem"]
    assert plain.converged and fast.converged
    assert fast.history[-1]["log_evidence"] >= plain.history[-1]["log_evidence"] - 1e-6
    np.testing.assert_allclose(fast.system.A, plain.system.A, atol=2e-3)
    np.testing.assert_allclose(
        fast.system.obs_noise.covariance(), plain.system.obs_noise.covariance(), atol=2e-3
    )
    assert 2 * fast.epochs < plain.epochs


@pytest.mark.slow  # SQUAREM's fixed point (≈ 5 s); exact EM on the linear-Gaussian model stays
def test_squarem_stops_at_an_em_fixed_point_before_plain_em():
    """The test above at a fifth of its cost: SQUAREM converges (17 epochs), one plain EM epoch
    from its answer moves nothing (an EM fixed point; measured 2e-7), and plain EM given twice
    SQUAREM's epochs has not converged (A still 0.04 away, log-evidence 1.2 nats lower)."""
    y, (_, C, _, _, mu0, P0) = _lg_problem(T=60)
    A0, _, Q0, R0 = _guess()
    data = ceemx.Trajectories(jnp.asarray(y))

    def run(system, states, acceleration, epochs):
        return ceemx.fit(
            system,
            data,
            states,
            solver=ceemx.LaplaceEM(acceleration=acceleration, rtol=1e-9),
            trainable=lambda s: (s.A, s.process_noise, s.obs_noise),
            max_epochs=epochs,
            outliers="keep",
        )

    start = _system(A0, C, Q0, R0, mu0, P0)
    x0 = jnp.zeros(y.shape[:2] + (2,))
    fast = run(start, x0, "squarem", 400)
    assert fast.converged
    plain = run(start, x0, None, 2 * fast.epochs)
    assert not plain.converged and plain.epochs == 2 * fast.epochs
    assert fast.history[-1]["log_evidence"] > plain.history[-1]["log_evidence"]
    step = run(fast.system, fast.states, None, 1)
    _assert_same_model(step, fast, 1e-5)


@pytest.mark.slow  # ≈ 5 s; noise learning on the linear-Gaussian model stays in the default suite
def test_learned_diagonal_noise_with_missing_data():
    """Diagonal scales (one per component) are recovered with a third of the outputs missing."""
    rng = np.random.default_rng(3)
    A = jnp.asarray([[0.95, 0.1], [-0.1, 0.9]])
    C = jnp.eye(2)
    truth = ceemx.systems.LinearSystem(
        A, C, process_noise=jnp.asarray([0.1, 0.2]), obs_noise=jnp.asarray([0.3, 0.5])
    )
    x1 = jnp.asarray(rng.normal(size=(4, 2)))
    _, data = ceemx.simulate(truth, jax.random.PRNGKey(0), x1, 400)
    mask = rng.uniform(size=data.y.shape) > 1 / 3
    data = ceemx.Trajectories(data.y, mask=jnp.asarray(mask))
    guess = ceemx.systems.LinearSystem(
        A, C, process_noise=jnp.asarray([0.5, 0.5]), obs_noise=jnp.asarray([1.0, 1.0])
    )
    res = ceemx.fit(
        guess,
        data,
        solver=ceemx.LaplaceEM(),
        trainable=lambda s: (s.A, s.process_noise, s.obs_noise),
        max_epochs=500,
        outliers="keep",
    )
    assert res.converged
    ev = res.history_array("log_evidence")
    assert np.all(np.diff(ev) > -1e-6 * np.abs(ev[1:]))  # monotone up to round-off
    se = res.standard_errors()  # observed information of the Laplace evidence (exact here)
    for field, truth in (("process_noise", [0.1, 0.2]), ("obs_noise", [0.3, 0.5])):
        est = np.asarray(getattr(res.system, field).scale)
        err = np.asarray(getattr(se, field).scale)
        assert np.all((err > 0) & (err < 0.2 * est)), (field, est, err)
        assert np.all(np.abs(est - truth) < 3 * err), (field, est, err)


@pytest.mark.parametrize("solver", [ceemx.Alternating(), ceemx.JointLM(), ceemx.ParticleEM()])
def test_certainty_equivalent_methods_refuse_trainable_noise(solver):
    y, params = _lg_problem(B=1, T=10)
    with pytest.raises(ValueError, match="LaplaceEM"):
        ceemx.fit(
            _system(*params),
            ceemx.Trajectories(jnp.asarray(y)),
            solver=solver,
            trainable=lambda s: (s.A, s.obs_noise),
        )


def test_learned_noise_needs_a_gaussian_model():
    y, (A, C, Q, R, mu0, P0) = _lg_problem(B=1, T=10)
    system = ceemx.systems.LinearSystem(
        jnp.asarray(A), jnp.asarray(C), obs_noise=ceemx.StudentT(0.3, 4.0, 2)
    )
    with pytest.raises(ValueError, match="DiagonalGaussian or CholeskyGaussian"):
        ceemx.fit(
            system,
            ceemx.Trajectories(jnp.asarray(y)),
            solver=ceemx.LaplaceEM(),
            trainable=lambda s: (s.A, s.obs_noise),
        )


@pytest.mark.slow  # 24 particle filters of 5000 particles (≈ 40 s)
def test_laplace_evidence_matches_the_particle_filter_likelihood():
    """On the Figure-2 Lorenz setting the Laplace log-evidence follows log p(y | θ) (particle
    filter, fully adapted, 5000 particles) within ~1 nat across σ_w, and both peak at the same
    σ_w — where Laplace EM's learned σ_w of this seed (45) lies, 25 % below the truth 0.1."""
    import math

    from ceemx.experiments import common
    from ceemx.inference.particle import particle_filter
    from ceemx.models import with_noise

    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
    p = common.lorenz_problem(45, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False)
    prior = common.lorenz_initial_prior(1)
    base = eqx.tree_at(lambda s: s.initial_prior, true, prior, is_leaf=lambda v: v is None)
    grid = (0.07, 0.075, 0.09, 0.1)
    lap, pf = [], []
    for sw in grid:
        s = with_noise(base, sw, 0.5)
        sol = ceemx.smooth(s, p.data, p.states, ceemx.LMSmoother(rtol=1e-14), covariance=True)
        ell = -sol.objective + 0.5 * 128 * 3 * math.log(2 * math.pi) - 0.5 * sol.log_det
        lap.append(float(jnp.sum(ell)))
        runs = [
            float(jnp.sum(particle_filter(s, p.data, n_particles=5000, key=k).log_likelihood))
            for k in jax.random.split(jax.random.PRNGKey(0), 6)
        ]
        pf.append(float(np.mean(runs)))
    lap, pf = np.asarray(lap), np.asarray(pf)
    np.testing.assert_allclose(lap, pf, atol=1.0)
    assert np.argmax(lap) <= 1 and np.argmax(pf) <= 1  # σ_w ≈ 0.07–0.075 is the likelier
    assert min(pf[0], pf[1]) - pf[3] > 3.0  # ... by several nats over the truth 0.1


def test_parameters_saturated_at_a_bound_survive_learned_noise():
    """A constrained parameter at its bound in float64 (sigmoid = 1.0 exactly) must not break
    the noise split (natural → unconstrained would give ±∞): θ stays in unconstrained units."""
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers.laplace import _NoiseSplit

    class Bounded(ceemx.AbstractSystem):
        a: jax.Array = ceemx.param(lower=0.1, upper=1.0)

        @property
        def state_dim(self):
            return 1

        @property
        def obs_dim(self):
            return 1

        def dynamics(self, x, u, t):
            return self.a * x

        def observe(self, x, u, t):
            return x

    system = Bounded(a=jnp.asarray(0.5), process_noise=0.1, obs_noise=0.2)
    data = ceemx.Trajectories(jnp.ones((1, 5, 1)))
    problem, theta = FitProblem.create(
        system, data, trainable=lambda s: (s.a, s.process_noise, s.obs_noise)
    )
    from jax.flatten_util import ravel_pytree

    unravel = ravel_pytree(problem.template)[1]
    # sigmoid(60) == 1.0 in float64: a is at its upper bound.
    theta = ravel_pytree(eqx.tree_at(lambda s: s.a, unravel(theta), jnp.asarray(60.0)))[0]
    split = _NoiseSplit(problem, theta)
    assert split.inner is not None
    built = problem.build(theta)
    assert float(built.a) == 1.0
    noisier = eqx.tree_at(lambda s: s.obs_noise, built, ceemx.DiagonalGaussian(0.3, 1))
    joined = split.join(split.theta_inner, noisier)
    assert np.all(np.isfinite(joined)) and float(unravel(joined).a) == 60.0
    assert float(problem.build(joined).obs_noise.scale) == pytest.approx(0.3)


def test_quasi_newton_bfgs_update_keeps_the_secant_and_positive_definite():
    """The damped BFGS update of the quasi-Newton acceleration: H⁻¹y = s where sᵀy is large
    enough; positive definite (and no secant) where the objective is not concave along s."""
    from ceemx.identification.solvers.laplace_qn import bfgs_update

    rng = np.random.default_rng(0)
    M = rng.normal(size=(4, 4))
    Hinv = M @ M.T + np.eye(4)
    s = rng.normal(size=4)
    y = np.linalg.solve(Hinv, s) + 0.1 * s  # sᵀy > 0.2 sᵀBs
    new = bfgs_update(Hinv, s, y)
    np.testing.assert_allclose(new @ y, s, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(new, new.T, atol=1e-12)
    bad = bfgs_update(Hinv, s, -y)  # negative curvature along s: damped, still positive definite
    assert np.all(np.linalg.eigvalsh(0.5 * (bad + bad.T)) > 0)
    np.testing.assert_array_equal(bfgs_update(Hinv, np.zeros(4), y), Hinv)


@pytest.mark.slow  # two Laplace EM fits and FD evidences (145 s at load 25)
def test_quasi_newton_reaches_the_em_fixed_point():
    """``acceleration="quasi_newton"`` on a linear-Gaussian model: its gradient is the gradient
    of the exact log-likelihood (Fisher's identity; central differences of the Kalman evidence
    to 1e-6 relative), and it ends at SQUAREM's answer (A, Q, R to 1e-4, the evidence no lower),
    where one plain EM update moves nothing (1e-6): the EM fixed point, the MLE."""
    from ceemx.identification.problem import FitProblem
    from ceemx.identification.solvers.laplace_qn import q_derivatives
    from ceemx.inference.posterior import E_STEP_SMOOTHER, gaussian_posterior
    from ceemx.lib.tree import trace_numbers

    y, (_, C, _, _, mu0, P0) = _lg_problem(T=60)
    A0, _, Q0, R0 = _guess()
    data = ceemx.Trajectories(jnp.asarray(y))
    x0 = jnp.zeros(y.shape[:2] + (2,))
    start = _system(A0, C, Q0, R0, mu0, P0)

    def trainable(s):
        return (s.A, s.process_noise, s.obs_noise)

    problem, theta = FitProblem.create(start, data, trainable=trainable)
    smoother = trace_numbers(E_STEP_SMOOTHER, jnp.float64)

    def evidence(th):
        post = gaussian_posterior(smoother, problem.build(th), x0, data)
        return float(jnp.sum(post.log_evidence)), post

    _, post = evidence(theta)
    grad = -np.asarray(q_derivatives(problem, theta, post, hessian=False)[1])
    h = 1e-5
    fd = np.array(
        [
            (evidence(theta.at[i].add(h))[0] - evidence(theta.at[i].add(-h))[0]) / (2 * h)
            for i in range(theta.shape[0])
        ]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * np.max(np.abs(fd)))

    def run(system, states, acceleration, epochs):
        return ceemx.fit(
            system,
            data,
            states,
            solver=ceemx.LaplaceEM(acceleration=acceleration, rtol=1e-12),
            trainable=trainable,
            max_epochs=epochs,
            outliers="keep",
            diagnose=False,
        )

    qn = run(start, x0, "quasi_newton", 200)
    sq = run(start, x0, "squarem", 400)
    assert qn.converged and sq.converged
    assert qn.history[-1]["log_evidence"] >= sq.history[-1]["log_evidence"] - 1e-8
    _assert_same_model(sq, qn, 1e-4)
    step = run(qn.system, qn.states, None, 1)
    _assert_same_model(step, qn, 1e-6)


@pytest.mark.slow  # four quasi-Newton fits, one at the coarse start's shapes (≈ 20 s)
def test_coarse_start_ends_at_the_same_fixed_point():
    """``coarse_start``: a fit on the first 150 steps of one of the three trajectories starts the
    fit on all of them (θ and, scaled by 150/600, the BFGS curvature); it ends at the fit's
    fixed point without it (evidence to 1e-8, A, Q, R to 1e-6) in fewer epochs on all the data.
    From a start the coarse fit cannot improve on (the optimum itself) the start stands, and
    the fit is the one without the coarse start, bit for bit."""
    y, (_, C, _, _, mu0, P0) = _lg_problem(T=200)
    A0, _, Q0, R0 = _guess()
    data = ceemx.Trajectories(jnp.asarray(y))
    x0 = jnp.zeros(y.shape[:2] + (2,))

    def run(system, states, coarse):
        return ceemx.fit(
            system,
            data,
            states,
            solver=ceemx.LaplaceEM(acceleration="quasi_newton", rtol=1e-12, coarse_start=coarse),
            trainable=lambda s: (s.A, s.process_noise, s.obs_noise),
            max_epochs=200,
            outliers="keep",
            diagnose=False,
        )

    start = _system(A0, C, Q0, R0, mu0, P0)
    plain, coarse = run(start, x0, None), run(start, x0, 150)
    assert plain.converged and coarse.converged
    first = coarse.history[0]
    assert first["coarse_used"] and first["coarse_converged"] and first["coarse_steps"] == 150
    assert not any(k.startswith("coarse") for k in coarse.history[1])
    assert not any(k.startswith("coarse") for k in plain.history[0])
    assert coarse.epochs < plain.epochs, (coarse.epochs, plain.epochs)
    ev = [r.history[-1]["log_evidence"] for r in (plain, coarse)]
    np.testing.assert_allclose(ev[1], ev[0], rtol=0, atol=1e-8)
    _assert_same_model(coarse, plain, 1e-6)
    kept = run(plain.system, plain.states, 150)
    assert kept.history[0]["coarse_converged"] and kept.history[0]["coarse_used"] is False
    same = run(plain.system, plain.states, None)
    np.testing.assert_array_equal(kept.theta, same.theta)
    assert kept.epochs == same.epochs


@pytest.mark.slow  # ≈ 3 s (a Lorenz program); the exact-EM test checks the same code linear
def test_expected_dynamics_terms_evaluate_each_distinct_previous_state_once():
    """The pair points of a lower-triangular root keep x_t at its mean in 2n of their 4n points
    (bitwise): the expected objective evaluates the dynamics at the 2n + 1 distinct x_t and
    equals the sum over all 4n pair points (1e-13), as do the M-step's value and θ-gradient
    (nonlinear: Lorenz, n = 3)."""
    from ceemx.experiments import common
    from ceemx.identification.learning.expected import cubature_points
    from ceemx.identification.problem import FitProblem
    from ceemx.inference.objective import expected_neg_log_joint_single, linearize_expected

    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
    p = common.lorenz_problem(43, true, B=1, T=6, sigma_w=0.1, sigma_v=0.5, coupling=False)
    rng = np.random.default_rng(0)
    T, n = p.states.shape[1], p.states.shape[2]
    M = rng.normal(size=(T * n, T * n))
    S = 0.05 * (M @ M.T) / (T * n) + 0.01 * np.eye(T * n)  # a joint posterior covariance
    blocks = S.reshape(T, n, T, n)
    cov = jnp.asarray(np.stack([blocks[t, :, t] for t in range(T)]))[None]
    cross = jnp.asarray(np.stack([blocks[t + 1, :, t] for t in range(T - 1)]))[None]
    problem, theta = FitProblem.create(true, p.data, trainable=common.LORENZ_PARAMS)
    d = p.data

    @eqx.filter_jit
    def both(problem, theta, states, cov, cross):
        points, pairs = cubature_points(states, cov, cross)
        pts, prs = points[0], pairs[0]
        system = problem.build(theta)

        def every_point(th):  # the rule's sum over all 4n pair points
            s = problem.build(th)
            ts = jnp.arange(T)
            r_obs = jax.vmap(lambda xs, y, u, t: jax.vmap(lambda x: y - s.observe(x, u, t))(xs))(
                pts, d.y[0], d.u[0], ts
            )
            r_dyn = jax.vmap(
                lambda zs, u, t: jax.vmap(lambda z: z[n:] - s.dynamics(z[:n], u, t))(zs)
            )(prs, d.u[0, :-1], ts[:-1])
            mk = jnp.repeat(d.mask[0][:, None], pts.shape[1], axis=1)
            obs = jax.vmap(s.obs_noise.nll)(
                r_obs.reshape(-1, r_obs.shape[-1]), mk.reshape(-1, mk.shape[-1])
            )
            dyn = jax.vmap(s.process_noise.nll)(r_dyn.reshape(-1, n))
            total = jnp.sum(obs) / pts.shape[1] + jnp.sum(dyn) / prs.shape[1]
            if s.initial_prior is not None:
                total = total + jnp.mean(jax.vmap(s.initial_prior.nll)(pts[0]))
            return total

        fast = expected_neg_log_joint_single(system, pts, prs, d.y[0], d.u[0], d.mask[0])
        lin = linearize_expected(problem.build, theta, pts, prs, d.y[0], d.u[0], d.mask[0])
        ref, ref_grad = jax.value_and_grad(every_point)(theta)
        return pairs, fast, lin, ref, ref_grad

    pairs, fast, (value, grad, _), ref, ref_grad = both(problem, theta, p.states, cov, cross)
    x_prev = np.asarray(p.states[0, :-1])
    for block in (slice(n, 2 * n), slice(3 * n, 4 * n)):  # x_t exactly at its mean
        np.testing.assert_array_equal(
            np.asarray(pairs[0, :, block, :n]), np.repeat(x_prev[:, None], n, 1)
        )
    assert not np.allclose(pairs[0, :, :n, :n], x_prev[:, None])  # the others move it
    np.testing.assert_allclose(fast, ref, rtol=1e-13)
    np.testing.assert_allclose(value, ref, rtol=1e-13)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-10, atol=1e-10 * np.max(np.abs(ref_grad)))


@pytest.mark.slow  # ≈ 3 s (a Lorenz program, as the test above)
def test_padding_after_the_last_observation_leaves_the_m_step_and_noise_statistics():
    """A record padded with masked steps (a shorter record of a ragged batch): the M-step's
    value, θ-gradient and Gauss–Newton matrix and the noise statistics equal those of the record
    alone, whatever the posterior over the padding (the states after the last observation
    integrate out of p(y | θ)). They counted the padding's expected dynamics terms: fits of a
    nonlinear model moved with the amount of padding (a = 0.81 → 0.92)."""
    from ceemx.experiments import common
    from ceemx.identification.learning.expected import cubature_points
    from ceemx.identification.noise_moments import noise_second_moments
    from ceemx.identification.problem import FitProblem
    from ceemx.inference.objective import expected_neg_log_joint_single, linearize_expected

    true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, process_noise=0.1, obs_noise=0.5)
    p = common.lorenz_problem(43, true, B=1, T=6, sigma_w=0.1, sigma_v=0.5, coupling=False)
    d, T, n, extra = p.data, p.states.shape[1], p.states.shape[2], 4
    rng = np.random.default_rng(1)
    cov = jnp.asarray(np.broadcast_to(0.02 * np.eye(n), (1, T + extra, n, n)).copy())
    cov = cov.at[:, T:].set(30.0 * np.eye(n))  # the padding's posterior: wide, anything
    cross = jnp.asarray(0.01 * rng.normal(size=(1, T + extra - 1, n, n)))
    states = jnp.concatenate([p.states, 5.0 + jnp.asarray(rng.normal(size=(1, extra, n)))], 1)

    def padded(a, value):
        return jnp.concatenate([a, jnp.full(a.shape[:1] + (extra,) + a.shape[2:], value)], 1)

    d_pad = ceemx.Trajectories(padded(d.y, 0.0), padded(d.u, 0.0), padded(d.mask, False))
    problem, theta = FitProblem.create(true, d, trainable=common.LORENZ_PARAMS)

    @eqx.filter_jit
    def terms(problem, theta, states, cov, cross, data):
        points, pairs = cubature_points(states, cov, cross)
        system = problem.build(theta)
        one = (points[0], pairs[0], data.y[0], data.u[0], data.mask[0])
        value = expected_neg_log_joint_single(system, *one)
        lin = linearize_expected(problem.build, theta, *one)
        moments = noise_second_moments(system, points, pairs, data, jnp.ones(1))
        return value, lin, moments

    alone = terms(problem, theta, states[:, :T], cov[:, :T], cross[:, : T - 1], d)
    pad = terms(problem, theta, states, cov, cross, d_pad)
    for got, want in zip(jax.tree.leaves(pad), jax.tree.leaves(alone), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
