"""Hybrid models: a learned term inside a physics model.

(``systems.hybrid`` and ``identification.hybrid_builder``.)
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array

import ceemx
from ceemx.evaluation.early_stopping import EarlyStopping
from ceemx.identification.hybrid_builder import hybrid
from ceemx.identification.problem import trainable_mask
from ceemx.inference.objective import log_joint
from ceemx.systems.hybrid import HybridContinuous
from ceemx.systems.learned_term import learned_term, weight_decay

DT = 0.1


class Oscillator(ceemx.AbstractContinuousSystem):
    """ẍ = −k x − k₃ x³ − c ẋ + u, y = x: a Duffing oscillator (linear when k₃ = 0)."""

    k: Array = ceemx.param(positive=True)
    c: Array = ceemx.param(positive=True)
    k3: Array = ceemx.param(fixed=True, default=0.0)

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 1

    @property
    def control_dim(self):
        return 1

    def vector_field(self, x, u, t):
        return jnp.stack([x[1], -self.k * x[0] - self.k3 * x[0] ** 3 - self.c * x[1] + u[0]])

    def observe(self, x, u, t):
        return x[:1]


def multisine(T: int) -> Array:
    t = jnp.arange(T, dtype=jnp.float64) * DT
    u = jnp.sin(0.7 * t) + 0.6 * jnp.sin(1.9 * t + 1.0) + 0.4 * jnp.sin(3.1 * t + 2.0)
    return (2.0 * u)[None, :, None]


def simulate(system, u, x1=None):
    x1 = jnp.zeros(system.state_dim) if x1 is None else x1

    def step(x, ut):
        return system.dynamics(x, ut, 0.0), x

    return jax.lax.scan(step, x1, u[0])[1][None]


@pytest.fixture(scope="module")
def duffing():
    """The truth (k₃ = 1), the linear physics model that misses the cubic term, and data."""
    T = 400
    true = Oscillator(1.0, 0.3, 1.0, dt=DT, process_noise=1e-3, obs_noise=0.01)
    physics = Oscillator(1.0, 0.3, 0.0, dt=DT, process_noise=1e-3, obs_noise=0.01)
    u = multisine(T)
    x = simulate(true, u)
    y = x[..., :1] + 0.01 * jax.random.normal(jax.random.PRNGKey(0), x[..., :1].shape)
    return true, physics, x, ceemx.Trajectories(y, u)


def test_zero_initialised_hybrid_is_the_physics_model(duffing):
    """J, the free run and the physics gradient of a fresh hybrid equal the physics model's, and
    the output layer's gradient is not zero (the weights learn from the first step)."""
    _, physics, x, data = duffing
    h = hybrid(physics, data, states=x, dynamics=True, observation=True)
    assert isinstance(h, HybridContinuous)

    @eqx.filter_jit
    def both(physics, h):
        def J(model):
            return jnp.sum(log_joint(model, x, data))

        g_phys = jax.grad(lambda k: J(eqx.tree_at(lambda s: s.k, physics, k)))(physics.k)
        g_h = jax.grad(lambda k: J(eqx.tree_at(lambda s: s.physics.k, h, k)))(h.physics.k)
        last = h.dynamics_term.net.layers[-1].weight
        g_last = jax.grad(
            lambda w: J(eqx.tree_at(lambda s: s.dynamics_term.net.layers[-1].weight, h, w))
        )(last)
        values = (log_joint(h, x, data), log_joint(physics, x, data))
        return values, (g_h, g_phys), g_last

    (J_h, J_p), (g_h, g_p), g_last = both(physics, h)
    assert float(jnp.max(jnp.abs(J_h - J_p))) == 0.0
    # each free run its own program, as a user runs them (one program would fuse the two
    # differently and differ in the last bit)
    np.testing.assert_array_equal(simulate(h, data.u), simulate(physics, data.u))
    assert float(g_h) == pytest.approx(float(g_p), rel=1e-12)
    assert float(jnp.max(jnp.abs(g_last))) > 0.0


def test_trainable_parts_and_noise_never_selected(duffing):
    _, physics, x, data = duffing
    # The default network, (x, u) → 16 → 16 → 1: its initialisation is the one compiled for the
    # observation term of test_zero_initialised_hybrid_is_the_physics_model.
    h = hybrid(physics, data, states=x, dynamics=(1,))

    def count(trainable):
        return sum(
            np.size(leaf)
            for leaf in jax.tree_util.tree_leaves(eqx.filter(h, trainable_mask(h, trainable)))
        )

    n_net = (3 * 16 + 16) + (16 * 16 + 16) + (16 * 1 + 1)  # one output: the velocity equation
    assert count(h.trainable("physics")) == 2  # k, c (k3 fixed; noise models never)
    assert count(h.trainable("term")) == n_net
    assert count(h.trainable("both")) == 2 + n_net
    assert count(None) == 2 + n_net  # the default: no noise, no statistics, no fixed k3
    with pytest.raises((ValueError, TypeError), match="part"):
        h.trainable("weights")  # type: ignore[arg-type]
    # weight decay: −½‖w‖²/σ² of the network's leaves
    lp = weight_decay(h)
    leaves = jax.tree_util.tree_leaves(eqx.filter(h.dynamics_term.net, eqx.is_inexact_array))
    assert float(lp) == pytest.approx(-0.5 * sum(float(jnp.sum(w**2)) for w in leaves))


def test_bounded_state_free_run_stays_inside():
    """A level that the physics would drive negative stays ≥ 0 in a free run."""

    class Drain(ceemx.AbstractContinuousSystem):
        k: Array = ceemx.param(positive=True)

        @property
        def state_dim(self):
            return 1

        @property
        def obs_dim(self):
            return 1

        def vector_field(self, x, u, t):
            return -self.k * jnp.ones_like(x)  # a constant outflow: empties, then goes negative

        def observe(self, x, u, t):
            return x

    physics = Drain(1.0, dt=0.5)
    T = 40
    data = ceemx.Trajectories(jnp.linspace(5.0, 0.0, T)[None, :, None])
    x = data.y
    free = simulate(physics, data.u, jnp.array([5.0]))
    assert float(free.min()) < -10.0
    h = hybrid(physics, data, states=x, lower=0.0)
    bounded = simulate(h, data.u, jnp.array([5.0]))
    assert float(bounded.min()) >= 0.0
    # far from the bound the projection is the identity (to e^{−β·distance}/β)
    np.testing.assert_allclose(bounded[0, :6], free[0, :6], atol=1e-9)


def test_learned_term_validation(duffing):
    _, physics, x, data = duffing
    key = jax.random.PRNGKey(0)
    zero, one = jnp.zeros(1), jnp.ones(1)
    with pytest.raises(ValueError, match="`x_scale` must be positive"):
        learned_term(key, x_mean=zero, x_scale=zero, out_scale=one)
    with pytest.raises(ValueError, match="`targets`"):
        learned_term(key, x_mean=zero, x_scale=one, out_scale=one, targets=(3,), size=2)
    with pytest.raises(ValueError, match="`states` must have shape"):
        hybrid(physics, data, states=x[:, :10])
    with pytest.raises(ValueError, match="at least one learned term"):
        hybrid(physics, data, states=x, dynamics=False)
    with pytest.raises(ValueError, match="`lower` must be below `upper`"):
        hybrid(physics, data, states=x, lower=1.0, upper=0.0)
    with pytest.raises(TypeError, match="physics"):
        hybrid("not a model", data, states=x)  # type: ignore[arg-type]
    # Adversarial arguments: each refused by name before any statistics are computed.
    wrong_m = ceemx.Trajectories(jnp.concatenate([data.y, data.y], -1), data.u)
    with pytest.raises(ValueError, match="`data.y` has m = 2"):
        hybrid(physics, wrong_m, states=x)
    with pytest.raises(ValueError, match="`lower` must not be NaN"):
        hybrid(physics, data, states=x, lower=float("nan"))
    with pytest.raises(ValueError, match="scalars or 2-vectors; got shapes \\(3,\\)"):
        hybrid(physics, data, states=x, lower=jnp.zeros(3))
    with pytest.raises(TypeError, match="`dynamics` must be a bool or a sequence"):
        hybrid(physics, data, states=x, dynamics="yes")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="`key` must be a JAX PRNG key"):
        hybrid(physics, data, states=x, key=3)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="`activation` must be a callable"):
        hybrid(physics, data, states=x, activation=3)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="`n_init`"):
        EarlyStopping(data, n_init=0)
    with pytest.raises(ValueError, match="`score_options` has unknown keys \\['bogus'\\]"):
        EarlyStopping(data, n_init=5, score_options={"bogus": 1})
    with pytest.raises(TypeError, match="`start` must be a ceemx.AbstractSystem"):
        EarlyStopping(data, n_init=5, start="physics")  # type: ignore[arg-type]


@pytest.mark.slow  # one JointLM fit of ≈ 350 weights (≈ 25 s)
def test_hybrid_learns_the_missing_cubic_stiffness(duffing):
    """A linear oscillator misses the Duffing term −k₃x³; the hybrid's learned term on the
    velocity equation recovers it along the training record and the free run drops to the
    noise floor.

    Tolerances: the term is compared with −x³ on the training states (where data constrain it):
    RMS error ≤ 5 % of the RMS of x³ (measured 1.9 % at T = 1000); the free-run RMSE of the
    position (noise-free truth, measurement noise 0.01) ≤ 0.02 against 2.3 for the physics
    model alone (measured 0.004).
    """
    true, physics, x, data = duffing
    h = hybrid(physics, data, dynamics=(1,), width=16, depth=2)
    res = ceemx.fit(
        h,
        data,
        solver=ceemx.JointLM(),
        trainable=h.trainable("term"),
        log_prior=weight_decay,
        max_epochs=60,
        diagnose=False,
    )
    s = res.system
    term = jax.vmap(s.dynamics_term)(x[0], data.u[0])[:, 1]
    cubic = x[0, :, 0] ** 3
    rel = float(jnp.sqrt(jnp.mean((term + cubic) ** 2)) / jnp.sqrt(jnp.mean(cubic**2)))
    assert rel < 0.05, rel
    assert float(jnp.max(jnp.abs(jax.vmap(s.dynamics_term)(x[0], data.u[0])[:, 0]))) == 0.0
    rmse = float(jnp.sqrt(jnp.mean((simulate(s, data.u)[..., 0] - x[..., 0]) ** 2)))
    rmse_phys = float(jnp.sqrt(jnp.mean((simulate(physics, data.u)[..., 0] - x[..., 0]) ** 2)))
    assert rmse < 0.02 and rmse_phys > 1.0, (rmse, rmse_phys)


@pytest.mark.slow
def test_windows_sum_to_the_record(duffing):
    """Σ over windows of −J = the record's −J (exactly when the windows tile the T − 1 = 399
    transitions, 133 = 399 / 3; with 57 the last window's overlap adds its shared transitions
    once more), with the initial-state prior counted once; and the gradient likewise. One
    compiled program for all of it."""
    from ceemx.identification.learning.learning_problem import learning_problem, windowed
    from ceemx.identification.problem import FitProblem
    from ceemx.models import GaussianPrior

    _, physics, x, data = duffing
    prior = GaussianPrior(jnp.zeros(2), ceemx.DiagonalGaussian(jnp.ones(2), 2))
    system = eqx.tree_at(lambda s: s.initial_prior, physics, prior, is_leaf=lambda v: v is None)
    problem, theta = FitProblem.create(system, data)
    full = learning_problem(problem, theta, x)
    tiled, overlapping = windowed(full, 133), windowed(full, 57)
    assert (tiled.batch_size, overlapping.batch_size) == (3, 7)
    extra = 7 * 57 - 399  # transitions the last window of 57 repeats

    @eqx.filter_jit
    def terms(full, tiled, overlapping, th):
        sys1 = full.problem.build(th)
        r = x[0, 1:] - jax.vmap(lambda xt, ut: sys1.dynamics(xt, ut, 0.0))(
            x[0, :-1], data.u[0, :-1]
        )
        rep = jnp.sum(jax.vmap(sys1.process_noise.nll)(r[399 - 57 : 399 - 57 + extra]))
        values = (full.data_term(th), tiled.data_term(th), overlapping.data_term(th), rep)
        grads = (jax.grad(full.data_term)(th), jax.grad(tiled.data_term)(th))
        return values, grads

    (whole, total_tiled, total_overlap, rep), (g_full, g_tiled) = terms(
        full, tiled, overlapping, theta * 1.1
    )
    assert float(total_tiled) == pytest.approx(float(whole), rel=1e-12)
    np.testing.assert_allclose(g_tiled, g_full, rtol=1e-10)
    assert float(total_overlap) == pytest.approx(float(whole + rep), rel=1e-12)


def test_early_stopping_keeps_the_best_and_stops_after_patience(duffing):
    """Scores by the validation free run; the start counts as epoch 0; stops after `patience`
    epochs without improvement; a diverging (non-finite) model never becomes the best.

    The free runs start from the true x₁, passed through `score_options` to
    :func:`ceemx.benchmark_score` (which `EarlyStopping` calls): estimating it is benchmark_score's
    property (test_reliability, test_evaluate_real) and would compile its LM smoother (≈ 4 s)."""
    from ceemx.identification.fitting.result import EpochInfo

    true, physics, x, data = duffing
    worse = eqx.tree_at(lambda s: s.k, physics, jnp.asarray(3.0))
    nan_model = eqx.tree_at(lambda s: s.k, physics, jnp.asarray(1e300))
    stop = EarlyStopping(data, n_init=20, patience=2, start=physics, score_options={"x1": x[:, 0]})
    assert stop.best_epoch == 0 and stop.best_system is physics

    def epoch(k, system):
        return stop(EpochInfo(k, system, x, {}))

    assert epoch(1, worse) == {}
    assert epoch(2, true) == {}  # better: the new best
    assert stop.best_epoch == 2 and stop.best_system is true
    assert stop.best_rmse < 0.02 < stop.scores[0][1]
    errors, observed = stop.errors(true)  # the series the score is the RMSE of
    assert errors.shape == observed.shape == (data.batch_size, data.num_steps - 20, data.obs_dim)
    s = ceemx.benchmark_score(true, data, 20, x1=x[:, 0])
    want = float(np.sqrt(np.mean(np.square(np.asarray(s.rmse)))))
    assert stop.score(true) == pytest.approx(want, rel=1e-12)
    assert stop.best_rmse == pytest.approx(float(np.sqrt(np.mean(errors**2))), rel=1e-12)
    with pytest.warns(UserWarning, match="free-run simulation of trajectory 0 is not finite"):
        assert epoch(3, nan_model) == {}
    assert epoch(4, worse) is False  # two epochs without improvement
    assert stop.best_system is true


def test_constant_input_reads_the_raw_inputs():
    """``ConstantInput(model)`` on raw u is ``model`` on [u, 1], bit for bit; p counts the raw
    inputs; the inner model refuses the raw record."""
    from ceemx.systems import ConstantInput, LinearSystem

    inner = LinearSystem(
        jnp.array([[0.9, 0.1], [0.0, 0.8]]),
        jnp.array([[1.0, 0.0]]),
        B=jnp.array([[0.1, 0.2], [0.3, 0.05]]),
        D=jnp.array([[0.0, 0.5]]),
    )
    raw = ConstantInput(inner)
    assert (raw.input_dim, raw.state_dim, raw.obs_dim) == (1, 2, 1)
    assert raw.process_noise is inner.process_noise and raw.obs_noise is inner.obs_noise
    x, u = jnp.array([0.3, -0.2]), jnp.array([0.7])
    with_one = jnp.array([0.7, 1.0])
    for method in ("dynamics", "observe"):
        got, want = getattr(raw, method)(x, u, 3), getattr(inner, method)(x, with_one, 3)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    C, d = raw.linear_observation(u, 3)
    np.testing.assert_array_equal(np.asarray(C @ x + d), np.asarray(inner.observe(x, with_one, 3)))
    data = ceemx.Trajectories(jnp.zeros((1, 12, 1)), jnp.ones((1, 12, 1)))
    with pytest.raises(ValueError, match="shape"):  # the model itself wants the channel
        ceemx.free_run(inner, jnp.zeros((1, 2)), data.u)
    with pytest.raises(ValueError, match="takes no input"):
        ConstantInput(LinearSystem(jnp.eye(1), jnp.eye(1)))
    with pytest.raises(TypeError, match="must be a ceemx system"):
        ConstantInput(inner.A)


@pytest.mark.slow  # N4SID, a linear CE-EM fit and a JointLM fit of ≈ 100 weights
def test_black_box_route_scores_the_raw_record(duffing, tmp_path):
    """``ceemx.baselines.black_box``: the three models score the held-out record as measured
    (the route's models read the constant channel themselves), the refinement and the learned
    term improve on N4SID as the step-by-step route does, early stopping keeps its best epoch,
    and the neural model saves and loads."""
    from ceemx.baselines import black_box, with_constant_input

    true, _, _, data = duffing
    T = 400
    t = jnp.arange(T, dtype=jnp.float64) * DT
    u = 1.6 * (jnp.sin(0.5 * t + 0.3) + 0.6 * jnp.sin(2.3 * t) + 0.4 * jnp.sin(2.9 * t + 1.0))
    u = u[None, :, None]
    x = simulate(true, u)
    y = x[..., :1] + 0.01 * jax.random.normal(jax.random.PRNGKey(1), x[..., :1].shape)
    held_out = ceemx.Trajectories(y, u)  # raw: one input
    bb = black_box(data, state_dim=2, max_epochs=60, validation=held_out, n_init=20)
    scores = [
        float(ceemx.benchmark_score(m, held_out, 20).rmse[0, 0])
        for m in (bb.n4sid, bb.linear, bb.system)
    ]
    assert scores[1] <= 0.5 * scores[0], scores
    assert scores[2] <= scores[1] / 1.5, scores
    inner = ceemx.benchmark_score(bb.result.system, with_constant_input(held_out), 20)
    assert float(inner.rmse[0, 0]) == scores[2]  # the same model, the channel supplied
    assert bb.system.inner is bb.result.system and bb.system.input_dim == 1
    ceemx.save(tmp_path / "bb.ceemx", bb.system)
    loaded = ceemx.load(tmp_path / "bb.ceemx")
    assert float(ceemx.benchmark_score(loaded, held_out, 20).rmse[0, 0]) == scores[2]
    with pytest.raises(ValueError, match="n_init"):
        black_box(data, state_dim=2, validation=held_out)
    with pytest.raises(ValueError, match="state_dim"):
        black_box(data, state_dim=0)


@pytest.mark.slow  # N4SID, a linear CE-EM fit and a JointLM fit of ≈ 100 weights (≈ 21 s)
def test_neural_state_space_from_a_linear_start(duffing):
    """No physics: N4SID → CE-EM linear model → + learned term, scored on a held-out record.

    The Duffing data of the fixture; the held-out record is another multisine (other
    frequencies, 0.8× the amplitude), scored like the benchmarks (initial state from the first
    20 outputs, free run). Measured free-run RMSE: N4SID 2.54, the CE-EM linear model 0.472 (it
    fits simulation, N4SID one-step prediction), + learned term 0.218 (the cubic spring is what
    a linear model cannot represent). Asserted with margins of ≈ 2.7× and 1.45×: the refinement
    halves N4SID's error at least, the learned term takes 1.5× off the linear model's.
    """
    from ceemx.baselines import fit_affine_sid, refine_linear, with_constant_input

    true, _, _, data = duffing
    T = 400
    t = jnp.arange(T, dtype=jnp.float64) * DT
    u = 1.6 * (jnp.sin(0.5 * t + 0.3) + 0.6 * jnp.sin(2.3 * t) + 0.4 * jnp.sin(2.9 * t + 1.0))
    u = u[None, :, None]
    x = simulate(true, u)
    y = x[..., :1] + 0.01 * jax.random.normal(jax.random.PRNGKey(1), x[..., :1].shape)
    held_out = with_constant_input(ceemx.Trajectories(y, u))

    def score(model):
        return float(ceemx.benchmark_score(model, held_out, 20).rmse[0, 0])

    train = with_constant_input(data)
    n4sid = fit_affine_sid(data, state_dim=2)
    lin = refine_linear(n4sid, train, max_epochs=100)
    neural = hybrid(lin.system, train, states=lin.states, width=16, depth=1)
    res = ceemx.fit(
        neural,
        train,
        lin.states,
        solver=ceemx.JointLM(),
        trainable=neural.trainable("both"),
        log_prior=weight_decay,
        max_epochs=60,
        diagnose=False,
    )
    scores = score(n4sid), score(lin.system), score(res.system)
    assert scores[1] <= 0.5 * scores[0], scores
    assert scores[2] <= scores[1] / 1.5, scores
