"""Tests for the learning step (ceemx.learn, paper Eq. 11) and its four learners.

Oracles: the true Lorenz parameters (on exact, noise-free states the learning objective is
minimised at θ = (10, 28, 8/3) exactly), a SciPy BFGS minimisation of the very same objective
(``LearningProblem.value``) polished by dense Newton steps in NumPy, and the closed-form limits of
the ρ_θ term and of a dominating Gaussian prior. Sizes are tiny: a single Lorenz attractor
(n = 3, m = 2), T = 64, B = 1 (B = 2 for the minibatch test).
"""

import types

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optax
import pytest

import ceemx
from ceemx.identification.learning.step import make_problem
from ceemx.systems import CoupledLorenz, initial_states, random_observation_matrix

TRUE = np.array([10.0, 28.0, 8.0 / 3.0])
START = TRUE * np.array([1.08, 0.93, 1.05])  # every parameter within 10% of the truth
T = 64


# Jitted once per structure and shape: eager (op-by-op) evaluation costs seconds here.
simulate = eqx.filter_jit(ceemx.simulate)


@eqx.filter_jit
def value_of(problem, theta):
    return problem.value(theta)


def where_theta(s):
    return (s.sigma, s.rho, s.beta)


def theta_of(system):
    return np.array([system.sigma[0], system.rho[0], system.beta[0]])


def lorenz(theta, C, **kw):
    return CoupledLorenz(
        jnp.asarray([theta[0]]), jnp.asarray([theta[1]]), jnp.asarray([theta[2]]), C, **kw
    )


@pytest.fixture(scope="module")
def exact():
    """Single Lorenz, C ∈ R^{2×3}; the true noise-free states and exact observations (B = 1)."""
    C = random_observation_matrix(jax.random.PRNGKey(0), 1, m=2)
    assert C.shape == (2, 3)
    true = lorenz(TRUE, C)
    x1 = initial_states(jax.random.PRNGKey(1), 1, 1)
    states, data = simulate(
        true, jax.random.PRNGKey(2), x1, T, process_noise=False, obs_noise=False
    )
    return types.SimpleNamespace(C=C, true=true, start=lorenz(START, C), states=states, data=data)


@pytest.fixture(scope="module")
def noisy(exact):
    """Same system, noisy observations and perturbed states: the optimum is not the truth.

    The exact trajectory with white noise added in NumPy (observations: the system's noise scale
    0.01; states: 0.05, which dominates the process noise a noisy simulation would add): no
    second simulation program to compile."""
    rng = np.random.default_rng(5)
    states = exact.states + 0.05 * rng.standard_normal(exact.states.shape)
    y = exact.data.y + 0.01 * rng.standard_normal(exact.data.y.shape)
    data = eqx.tree_at(lambda d: d.y, exact.data, jnp.asarray(y))  # the same structure and shapes
    return types.SimpleNamespace(
        C=exact.C, start=exact.start, states=jnp.asarray(states), data=data
    )


# --------------------------------------------------------------------------------------------------
# All learners recover θ on exact states
# --------------------------------------------------------------------------------------------------

LEARNERS = {
    "lm": (lambda: ceemx.LMLearner(), 1e-6),
    "lbfgs": (lambda: ceemx.LBFGSLearner(max_steps=500), 1e-6),
    # Nelder–Mead stagnates on this ill-conditioned problem (curvatures 1e2–1e6 apart) at a point
    # that depends on round-off: measured 1e-8 and 5e-6 from the truth with XLA:CPU's two
    # emitters, whose objective values agree to 4e-16.
    "nelder_mead": (
        lambda: ceemx.NelderMeadLearner(rtol=1e-12, atol=1e-12, max_steps=5000),
        1e-5,
    ),
    "adam": (lambda: ceemx.OptaxLearner(optax.adam(1e-2), steps=3000), 1e-3),
}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.slow) if n in ("lbfgs", "nelder_mead", "adam") else n
        for n in LEARNERS
    ],
)
def test_learners_recover_true_parameters(exact, name):
    make, rtol = LEARNERS[name]
    learner = make()
    system, state, info = ceemx.learn(
        exact.start, exact.states, exact.data, learner, trainable=where_theta
    )
    assert isinstance(info, ceemx.LearnInfo)
    np.testing.assert_allclose(theta_of(system), TRUE, rtol=rtol)
    assert float(info.value_after) < float(info.value_before)
    assert np.isfinite(float(info.value_after))
    assert bool(info.status == ceemx.RESULTS.successful) or bool(
        info.status == ceemx.RESULTS.max_steps_reached
    )
    # The reported value is the learning objective at the returned θ.
    problem, theta = make_problem(system, exact.states, exact.data, trainable=where_theta)
    np.testing.assert_allclose(float(info.value_after), float(value_of(problem, theta)), rtol=1e-10)
    # Nothing but θ moved.
    np.testing.assert_array_equal(system.C, exact.start.C)
    np.testing.assert_array_equal(system.obs_noise.scale, exact.start.obs_noise.scale)
    if name == "adam":  # the optimiser state persists: (Adam state, PRNG key)
        opt_state, key = state
        assert int(opt_state[0].count) == 3000
    else:
        assert state is None


@pytest.mark.slow
def test_lm_and_lbfgs_agree_on_noisy_problem(noisy):
    lm, _, _ = ceemx.learn(noisy.start, noisy.states, noisy.data, trainable=where_theta)
    lb, _, _ = ceemx.learn(
        noisy.start, noisy.states, noisy.data, ceemx.LBFGSLearner(max_steps=500),
        trainable=where_theta,
    )  # fmt: skip
    np.testing.assert_allclose(theta_of(lm), theta_of(lb), rtol=1e-6)
    assert np.max(np.abs(theta_of(lm) / TRUE - 1)) > 1e-4  # a genuinely different optimum


# --------------------------------------------------------------------------------------------------
# ρ_θ and the log-prior
# --------------------------------------------------------------------------------------------------


@eqx.filter_jit
def _value_and_grad(problem, theta):
    return jax.value_and_grad(problem.value)(theta)


def dense_minimise(problem, theta0):
    """SciPy BFGS on ``problem.value`` with its JAX gradient (compiled once per structure)."""

    def fun(th):
        value, grad = _value_and_grad(problem, jnp.asarray(th))
        return float(value), np.asarray(grad)

    import scipy.optimize  # on use: each xdist worker imports every test module

    res = scipy.optimize.minimize(
        fun, np.asarray(theta0), jac=True, method="BFGS", options={"gtol": 1e-8, "maxiter": 2000}
    )
    # BFGS stops on "precision loss" near the optimum; require a small gradient relative to the
    # problem's scale (the objective is ~1e4 with curvature ~1e6 per parameter).
    assert np.max(np.abs(res.jac)) < 1e-2, res
    return np.asarray(res.x)


def gaussian_log_prior(mean, std):
    mean, std = jnp.asarray(mean), jnp.asarray(std)

    def log_prior(system):
        th = jnp.concatenate([system.sigma, system.rho, system.beta])
        return -0.5 * jnp.sum(((th - mean) / std) ** 2)

    return log_prior


# One log-prior object for every test that uses it: it is a static part of the learning problem,
# so sharing it shares the compiled learner.
PRIOR_MEAN = np.array([9.5, 27.0, 2.7])
PRIOR = gaussian_log_prior(PRIOR_MEAN, [0.05, 0.1, 0.01])


def test_huge_rho_theta_keeps_theta_at_start(noisy):
    system, _, info = ceemx.learn(
        noisy.start, noisy.states, noisy.data, trainable=where_theta, rho_theta=1e14
    )
    np.testing.assert_allclose(theta_of(system), START, rtol=1e-6)
    assert np.any(theta_of(system) != START)  # it still moved a little, towards the data
    assert float(info.value_after) <= float(info.value_before)


@pytest.mark.slow
def test_dominant_prior_moves_theta_to_prior_mean(exact):
    # Data weight tiny: enormous noise scales make −J nearly flat in θ; the prior is sharp.
    flat = lorenz(START, exact.C, process_noise=1e6, obs_noise=1e6)
    system, _, _ = ceemx.learn(
        flat, exact.states, exact.data, trainable=where_theta, log_prior=PRIOR
    )
    np.testing.assert_allclose(theta_of(system), PRIOR_MEAN, rtol=1e-6)


# "rho_theta" alone is a second oracle of the ρ_θ term: "both" checks it against the same BFGS
# oracle (with the prior's program, which "log_prior" compiles too) and
# test_huge_rho_theta_keeps_theta_at_start its closed-form limit.
@pytest.mark.parametrize(
    "case", [pytest.param("rho_theta", marks=pytest.mark.slow), "log_prior", "both"]
)
def test_lm_matches_dense_minimisation_with_regularisers(noisy, case):
    kw = {}
    if case in ("rho_theta", "both"):
        kw["rho_theta"] = 3e3
    if case in ("log_prior", "both"):
        kw["log_prior"] = PRIOR
    args = (noisy.start, noisy.states, noisy.data)
    system, _, info = ceemx.learn(*args, trainable=where_theta, **kw)
    problem, theta0 = make_problem(*args, trainable=where_theta, **kw)
    ref = dense_minimise(problem, theta0)
    np.testing.assert_allclose(theta_of(system), ref, rtol=1e-6)
    # The regulariser matters: the answer differs from the unregularised one.
    plain, _, _ = ceemx.learn(noisy.start, noisy.states, noisy.data, trainable=where_theta)
    assert np.max(np.abs(theta_of(system) / theta_of(plain) - 1)) > 1e-4
    assert float(info.value_after) <= float(info.value_before)


# --------------------------------------------------------------------------------------------------
# Monotonicity, trainable filters
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("max_steps", [1, 100])
def test_lm_learner_is_monotone(noisy, max_steps):
    _, _, info = ceemx.learn(
        noisy.start, noisy.states, noisy.data, ceemx.LMLearner(max_steps=max_steps),
        trainable=where_theta,
    )  # fmt: skip
    assert float(info.value_after) <= float(info.value_before)
    assert int(info.steps) <= max_steps


@pytest.mark.slow
def test_trainable_callable_selects_one_leaf(exact):
    system, _, _ = ceemx.learn(exact.start, exact.states, exact.data, trainable=lambda s: s.sigma)
    assert float(system.sigma[0]) != START[0]
    np.testing.assert_array_equal(system.rho, exact.start.rho)
    np.testing.assert_array_equal(system.beta, exact.start.beta)
    np.testing.assert_array_equal(system.C, exact.start.C)
    np.testing.assert_array_equal(system.H, exact.start.H)


@pytest.mark.slow
def test_trainable_boolean_filter_pytree(exact):
    spec = jtu.tree_map(lambda _: False, exact.start)
    spec = eqx.tree_at(lambda s: s.sigma, spec, replace=True)
    system, _, info = ceemx.learn(exact.start, exact.states, exact.data, trainable=spec)
    assert float(system.sigma[0]) != START[0]
    assert float(info.value_after) < float(info.value_before)
    np.testing.assert_array_equal(system.rho, exact.start.rho)
    np.testing.assert_array_equal(system.beta, exact.start.beta)
    np.testing.assert_array_equal(system.C, exact.start.C)


@pytest.mark.slow
def test_default_trainable_learns_model_arrays_not_noise(noisy):
    prior = ceemx.GaussianPrior(jnp.zeros(3), ceemx.DiagonalGaussian(jnp.full(3, 5.0), 3))
    start = lorenz(START, noisy.C, initial_prior=prior)
    system, _, info = ceemx.learn(start, noisy.states, noisy.data)
    assert float(info.value_after) < float(info.value_before)
    assert np.all(theta_of(system) != START)  # σ, ρ, β learn
    assert np.any(np.asarray(system.C) != np.asarray(start.C))  # C learns too (a model array)
    # H has no effect for K = 1 (own block masked): zero gradient, so it stays exactly put.
    np.testing.assert_array_equal(system.H, start.H)
    # Noise scales and the initial-state prior are not trained.
    np.testing.assert_array_equal(system.obs_noise.scale, start.obs_noise.scale)
    np.testing.assert_array_equal(system.process_noise.scale, start.process_noise.scale)
    np.testing.assert_array_equal(system.initial_prior.mean, prior.mean)
    np.testing.assert_array_equal(system.initial_prior.noise.scale, prior.noise.scale)


# --------------------------------------------------------------------------------------------------
# Minibatches
# --------------------------------------------------------------------------------------------------


def test_minibatch_optax_learner_decreases_objective(exact, noisy):
    # B = 2: the exact trajectory and its noisy copy (stacked in NumPy: no simulation to compile),
    # minibatches of one.
    states, data = (
        jax.tree.map(lambda a, b: jnp.asarray(np.concatenate([a, b])), e, n)
        for e, n in ((exact.states, noisy.states), (exact.data, noisy.data))
    )
    assert states.shape == (2, T, 3) and data.y.shape == (2, T, 2)
    learner = ceemx.OptaxLearner(optax.adam(1e-2), steps=200, batch_size=1)
    key = jax.random.PRNGKey(8)
    system, state, info = ceemx.learn(
        exact.start, states, data, learner, trainable=where_theta, key=key
    )
    assert bool(info.status == ceemx.RESULTS.successful)
    assert float(info.value_after) < float(info.value_before)
    # The reported values are those of the full-batch objective.
    problem, theta0 = make_problem(exact.start, states, data, trainable=where_theta)
    np.testing.assert_allclose(
        float(info.value_before), float(value_of(problem, theta0)), rtol=1e-12
    )
    assert np.max(np.abs(theta_of(system) / TRUE - 1)) < np.max(np.abs(START / TRUE - 1))
    # The minibatch key advanced and the state carries over to a second call.
    _, key_after = state
    assert not np.array_equal(jax.random.key_data(key_after), jax.random.key_data(key))
    system2, _, info2 = ceemx.learn(
        system, states, data, learner, trainable=where_theta, learner_state=state
    )
    assert float(info2.value_after) < float(info2.value_before)


def test_lm_driver_lazy_linearisation_takes_the_same_steps():
    """With ``value=`` the LM driver forms linearisations only at accepted points that continue,
    and takes exactly the eager driver's steps (Rosenbrock as a least-squares problem)."""
    import numpy as np

    from ceemx.lib.lm import levenberg_marquardt, marquardt_scale

    calls = {"eager": 0, "lazy": 0}

    def residual(z):
        return jnp.stack([10.0 * (z[1] - z[0] ** 2), 1.0 - z[0]])

    def make_evaluate(tag):
        def evaluate(z):
            jax.debug.callback(lambda: calls.__setitem__(tag, calls[tag] + 1))
            r = residual(z)
            J = jax.jacfwd(residual)(z)
            return 0.5 * r @ r, (J.T @ r, J.T @ J)

        return evaluate

    def solve(lin, lam):
        g, H = lin
        return jnp.linalg.solve(H + jnp.diag(marquardt_scale(jnp.diagonal(H), lam)), -g), True

    def run(tag, value):
        @jax.jit  # one program: eager evaluation compiles every operation around the loop
        def lm(z0):
            return levenberg_marquardt(
                make_evaluate(tag),
                lambda lin: lin[0],
                solve,
                lambda lin, d: d @ lin[1] @ d,
                z0,
                rtol=1e-14,
                atol=0.0,
                max_steps=200,
                damping=1e-3,
                value=value,
            )

        return jax.block_until_ready(lm(jnp.array([-1.2, 1.0])))

    eager = run("eager", None)
    lazy = run("lazy", lambda z: 0.5 * jnp.sum(residual(z) ** 2))
    np.testing.assert_allclose(np.asarray(lazy.z), [1.0, 1.0], atol=1e-8)
    np.testing.assert_array_equal(np.asarray(lazy.z), np.asarray(eager.z))
    assert int(lazy.steps) == int(eager.steps) and int(lazy.accepted) == int(eager.accepted)
    assert int(lazy.steps) > int(lazy.accepted)  # some trials were rejected
    assert lazy.lin is None
    # eager: the start plus every trial; lazy: the start plus accepted points that continued
    assert calls["eager"] == 1 + int(eager.steps)
    assert calls["lazy"] == int(lazy.accepted)

    # Under vmap (the smoother's use, one problem per trajectory), with the start's value taken
    # from the first linearisation: the same steps; no step at max_steps 0; a non-finite start
    # stops before any step.
    def batched(z0, steps):
        return jax.vmap(
            lambda z, k: levenberg_marquardt(
                lambda z: make_evaluate("lazy")(z),
                lambda lin: lin[0],
                solve,
                lambda lin, d: d @ lin[1] @ d,
                z,
                rtol=1e-14,
                atol=0.0,
                max_steps=k,
                damping=1e-3,
                value=lambda z: 0.5 * jnp.sum(residual(z) ** 2),
            )
        )(z0, steps)

    z0 = jnp.array([[-1.2, 1.0], [-1.2, 1.0], [0.5, jnp.nan]])
    out = jax.jit(batched)(z0, jnp.array([200, 0, 200], jnp.int32))
    np.testing.assert_array_equal(np.asarray(out.z[0]), np.asarray(eager.z))
    assert [int(k) for k in out.steps] == [int(eager.steps), 0, 0]
    np.testing.assert_array_equal(np.asarray(out.z[1]), [-1.2, 1.0])
    np.testing.assert_allclose(float(out.value[1]), 0.5 * float(jnp.sum(residual(z0[1]) ** 2)))
    assert float(out.damping[1]) == 1e-3
    R = ceemx.RESULTS
    expected = [R.successful, R.max_steps_reached, R.nonfinite]
    for b, status in enumerate(expected):
        assert bool(np.asarray(out.status == status)[b]), (b, out.status)


def test_lm_learner_max_accepted_is_the_first_accepted_step(noisy):
    """``max_accepted=1`` (Alternating's GEM default) stops at the LM's first accepted step: the
    point that ``max_steps`` = its iteration count reaches; the objective decreases."""
    assert ceemx.Alternating().learner == ceemx.LMLearner(max_accepted=1)
    gem, _, info = ceemx.learn(
        noisy.start, noisy.states, noisy.data, ceemx.LMLearner(max_accepted=1),
        trainable=where_theta,
    )  # fmt: skip
    k = int(info.steps)
    assert 1 <= k and float(info.value_after) < float(info.value_before)
    bounded, _, _ = ceemx.learn(
        noisy.start, noisy.states, noisy.data, ceemx.LMLearner(max_steps=k), trainable=where_theta
    )
    np.testing.assert_array_equal(theta_of(gem), theta_of(bounded))
    with pytest.raises(ValueError, match="max_accepted"):
        ceemx.LMLearner(max_accepted=0)
