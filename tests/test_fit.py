"""Tests for ceemx.fit (CE-EM, paper Algorithm 1): convergence, history, callbacks, compile-once,
failed trajectories, kill-and-resume from a checkpoint, state initialisation and input validation.

The shared problem is a single Lorenz attractor (n = 3) observed through a random C ∈ R^{2×3} with
σ_v = 0.01, simulated with tiny process noise (σ_w = 1e-3; the model assumes 0.01), T = 64, B = 2,
θ guesses within 10% of (10, 28, 8/3) and initial states = truth + N(0, 0.5²). Most tests reuse the
one compiled (smoother, learner) pair of this configuration.
"""

import json
import os
import signal
import subprocess
import sys
import textwrap
import types
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import ceemx
import ceemx.identification.initialize
import ceemx.identification.learning.step
import ceemx.inference.smoother
from ceemx.lib.results import codes
from ceemx.systems import CoupledLorenz, LinearSystem, initial_states, random_observation_matrix

RESULTS = ceemx.RESULTS
TRUE = np.array([10.0, 28.0, 8.0 / 3.0])
START = TRUE * np.array([1.08, 0.93, 1.05])
T, B = 64, 2


# Jitted once per structure and shape: eager (op-by-op) evaluation costs seconds here.
simulate = eqx.filter_jit(ceemx.simulate)
log_joint = eqx.filter_jit(ceemx.log_joint)


def where_theta(s):
    return (s.sigma, s.rho, s.beta)


def theta_of(system):
    return np.array([system.sigma[0], system.rho[0], system.beta[0]])


def lorenz(theta, C, dtype=jnp.float64):
    return CoupledLorenz(
        *(jnp.asarray([v], dtype) for v in theta), jnp.asarray(C, dtype),
        process_noise=0.01, obs_noise=0.01,
    )  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def traces():
    """Route ``fit``'s two compiled entry points through fresh jit wrappers that record each trace.

    A wrapper's Python body runs only while tracing. Every configuration (learner type and static
    options, batch shape, dtype) must be traced once per module: a second trace of the same one
    raises, whichever test causes it. The wrappers call the library's own compiled functions, so
    results are unchanged.
    """
    log = []
    smooth, learn = (
        ceemx.inference.smoother._smooth_batch,  # the compiled program (max_steps an argument)
        ceemx.identification.learning.step.run_learner,
    )

    def record(kind, key):
        if (kind, key) in log:
            raise AssertionError(f"{kind} retraced for an already compiled configuration {key}")
        log.append((kind, key))

    @eqx.filter_jit
    def smooth_traced(solver, max_steps, system, states, data, covariance):
        # The system's array types (weak or strong) are part of the configuration: the default
        # start smooths with a strongly typed process noise where a model may have a weak one.
        leaves = jax.tree_util.tree_leaves(eqx.filter(system, eqx.is_array))
        types_ = tuple(str(jax.typeof(a)) for a in leaves)
        record("smooth", (states.shape, str(states.dtype), types_))
        return smooth(solver, max_steps, system, states, data, covariance)

    @eqx.filter_jit
    def learn_traced(learner, problem, theta, state):
        # The learner's type and static options (its tree structure: max_steps, max_accepted).
        options = jax.tree_util.tree_structure(learner)
        key = (type(learner).__name__, problem.states.shape, str(theta.dtype), options)
        record("learn", key)
        return learn(learner, problem, theta, state)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ceemx.inference.smoother, "_smooth_batch", smooth_traced)
        mp.setattr(ceemx.identification.learning.step, "run_learner", learn_traced)
        yield log


@pytest.fixture(scope="module")
def prob():
    keys = jax.random.split(jax.random.PRNGKey(42), 5)
    C = random_observation_matrix(keys[0], 1, m=2)
    true = lorenz(TRUE, C)
    x1 = initial_states(keys[1], B, 1)
    states, data = simulate(true, keys[2], x1, T, process_noise=ceemx.DiagonalGaussian(1e-3, 3))
    x_init = states + 0.5 * jax.random.normal(keys[3], states.shape)
    return types.SimpleNamespace(
        C=C, true=true, start=lorenz(START, C), states=states, data=data, x_init=x_init, x1=x1,
        keys=keys,
    )  # fmt: skip


# The model assumes σ_w = 0.01 where the data have 1e-3: the end-of-fit noise check (tested in
# test_noise_diagnostics.py) would warn about it after every fit here; these tests skip it.
NO_NOISE_CHECK = {"diagnose": False}


def fit_a(prob, *, tol=1e-10, atol=0.0, learner=None, **kwargs):
    """``fit`` on the shared problem from its θ guesses and initial states, learning (σ, ρ, β)."""
    learner = ceemx.LMLearner() if learner is None else learner
    solver = ceemx.Alternating(learner=learner, rtol=tol, atol=atol)
    return ceemx.fit(
        prob.start, prob.data, prob.x_init, trainable=where_theta, solver=solver,
        **NO_NOISE_CHECK, **kwargs,
    )  # fmt: skip


@pytest.fixture(scope="module")
def fitted(prob):
    """The reference fit: default LM smoother and LM learner, run to convergence."""
    return fit_a(prob, max_epochs=100, tol=1e-8)


# --------------------------------------------------------------------------------------------------
# Convergence and history
# --------------------------------------------------------------------------------------------------


@pytest.mark.slow  # a convergence run; default: test_solver_table's Alternating optimum
def test_fit_recovers_lorenz_parameters(fitted):
    assert fitted.converged, fitted.history[-1]
    assert isinstance(fitted.solver, ceemx.Alternating)
    assert fitted.epochs == len(fitted.history) < 100
    np.testing.assert_allclose(theta_of(fitted.system), TRUE, rtol=1e-2)
    assert np.all(np.asarray(fitted.status == RESULTS.successful)), fitted.messages()
    assert fitted.states.shape == (B, T, 3)
    print(f"fit: {fitted.epochs} epochs, θ = {theta_of(fitted.system)}")


@pytest.mark.slow  # the convergence run's; default: test_max_epochs_bounds_the_fit
def test_fit_history_is_monotone_and_complete(prob, fitted):
    keys = {"J", "dtheta_norm", "dx_norm", "smooth_time", "learn_time"}
    keys |= {"learner_steps", "smoother_steps"}
    for i, rec in enumerate(fitted.history, start=1):
        assert keys <= set(rec), keys - set(rec)
        assert rec["epoch"] == i
        assert len(rec["J_per_trajectory"]) == B
        np.testing.assert_allclose(sum(rec["J_per_trajectory"]), rec["J"], rtol=1e-12)
        assert rec["smooth_time"] >= 0 and rec["learn_time"] >= 0
        assert rec["learner_steps"] >= 0 and rec["smoother_steps"] >= 0
        assert rec["dtheta_norm"] >= 0 and rec["dx_norm"] >= 0
    J = fitted.history_array("J")
    assert np.all(np.isfinite(J))
    assert np.all(np.diff(J) >= -1e-9 * np.abs(J[1:])), np.diff(J)
    assert J[0] >= fitted.initial_J
    J0 = float(np.sum(log_joint(prob.start, prob.x_init, prob.data)))
    np.testing.assert_allclose(fitted.initial_J, J0, rtol=1e-12)
    # J of the last record is J at the returned (x, θ).
    np.testing.assert_allclose(
        J[-1], float(np.sum(log_joint(fitted.system, fitted.states, prob.data))), rtol=1e-12
    )
    assert fitted.history[-1]["converged"] and not any(h["converged"] for h in fitted.history[:-1])
    # dθ shrinks as EM converges.
    assert fitted.history[-1]["dtheta_norm"] < 1e-2 * fitted.history[0]["dtheta_norm"]


@pytest.mark.slow  # a second convergence run
def test_loose_tolerance_converges_early(prob, fitted):
    res = fit_a(prob, max_epochs=100, tol=1e-3)
    assert res.converged
    assert res.epochs < fitted.epochs
    # Same iterates as the tight run, just fewer of them.
    J_tight = fitted.history_array("J")[: res.epochs]
    np.testing.assert_allclose(res.history_array("J"), J_tight, rtol=1e-12)


def test_max_epochs_bounds_the_fit(prob):
    res = fit_a(prob, max_epochs=2)
    assert res.epochs == 2 and not res.converged
    # The history's bookkeeping (on the convergence run in the slow tier: monotone and complete).
    for i, rec in enumerate(res.history, start=1):
        assert rec["epoch"] == i and len(rec["J_per_trajectory"]) == B
        np.testing.assert_allclose(sum(rec["J_per_trajectory"]), rec["J"], rtol=1e-12)
    J0 = float(np.sum(log_joint(prob.start, prob.x_init, prob.data)))
    np.testing.assert_allclose(res.initial_J, J0, rtol=1e-12)
    J_end = float(np.sum(log_joint(res.system, res.states, prob.data)))
    np.testing.assert_allclose(res.history_array("J")[-1], J_end, rtol=1e-12)
    res0 = fit_a(prob, max_epochs=0)
    assert res0.epochs == 0
    np.testing.assert_array_equal(theta_of(res0.system), START)
    np.testing.assert_array_equal(res0.states, prob.x_init)


# --------------------------------------------------------------------------------------------------
# Callbacks
# --------------------------------------------------------------------------------------------------


def _blas_threads() -> list[int]:
    import scipy.linalg  # noqa: F401  (the OpenBLAS behind XLA's LAPACK calls, loaded)
    from threadpoolctl import threadpool_info

    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_callbacks_merge_records_and_stop(prob):
    seen, blas = [], []

    def record(info):
        blas.append(_blas_threads())  # inside fit: one BLAS thread (ceemx.infra.runtime)
        assert isinstance(info, ceemx.EpochInfo)
        assert info.states.shape == (B, T, 3)
        assert isinstance(info.system, CoupledLorenz)
        seen.append((info.epoch, theta_of(info.system)))
        eps = float(np.max(np.abs(theta_of(info.system) / TRUE - 1)))
        return {"eps": eps, "epoch_sq": info.epoch**2}

    def nothing(info):
        return None

    def stop_at_3(info):
        return False if info.epoch == 3 else True

    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=2, user_api="blas"):  # as many as two cores give by default
        before = _blas_threads()
        res = fit_a(prob, max_epochs=50, callbacks=[record, nothing, stop_at_3])
        after = _blas_threads()
    assert res.epochs == 3
    assert not res.converged
    assert [e for e, _ in seen] == [1, 2, 3]
    for (epoch, th), rec in zip(seen, res.history, strict=True):
        assert rec["epoch_sq"] == epoch**2
        assert rec["eps"] == float(np.max(np.abs(th / TRUE - 1)))
    assert res.history[-1]["stop"] and not res.history[0]["stop"]
    np.testing.assert_array_equal(seen[-1][1], theta_of(res.system))
    assert res.history_array("eps").shape == (3,)
    assert blas and all(b and max(b) == 1 for b in blas)  # SciPy's OpenBLAS, at least
    assert max(before) == 2 and after == before  # restored after the fit


# --------------------------------------------------------------------------------------------------
# A trajectory whose smoothing fails
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "learner",
    [
        pytest.param(ceemx.LBFGSLearner(max_steps=50), marks=pytest.mark.slow),
        ceemx.OptaxLearner(optax.adam(1e-2), steps=50),
    ],
    ids=["lbfgs", "adam"],
)
def test_failed_trajectory_does_not_poison_gradient_learners(prob, learner):
    """Gradient-based learners differentiate the objective: the excluded trajectory's non-finite
    terms must not leak into the gradient (0 · ∞ = NaN through ``jnp.where``). Trajectory 1
    starts at 1e200 (the shared problem's shapes: its smoothing program is compiled already)."""
    x_bad = prob.x_init.at[1].set(1e200)
    with pytest.warns(UserWarning, match=r"smoothing failed.*\[1\]"):
        res = ceemx.fit(
            prob.start,
            prob.data,
            x_bad,
            trainable=where_theta,
            solver=ceemx.Alternating(learner=learner),
            max_epochs=2,
            **NO_NOISE_CHECK,
        )
    nonfinite = codes(RESULTS.nonfinite)
    assert all(h["learner_status"] != nonfinite for h in res.history), res.history
    assert np.all(np.isfinite(theta_of(res.system)))
    assert np.all(theta_of(res.system) != START)  # it learned


# --------------------------------------------------------------------------------------------------
# Kill and resume
# --------------------------------------------------------------------------------------------------


_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import ceemx
    from ceemx.systems import CoupledLorenz

    arrays = np.load(sys.argv[1])
    th = arrays["start"]
    start = CoupledLorenz(
        jnp.asarray(th[:1]), jnp.asarray(th[1:2]), jnp.asarray(th[2:]), jnp.asarray(arrays["C"]),
        process_noise=0.01, obs_noise=0.01,
    )
    data = ceemx.Trajectories(jnp.asarray(arrays["y"]))

    def callback(info):
        print(f"EPOCH {info.epoch}", flush=True)
        if info.epoch == 4:  # epoch 4 is computed but its checkpoint is not yet written
            os.kill(os.getpid(), signal.SIGKILL)

    ceemx.fit(
        start, data, jnp.asarray(arrays["x_init"]), trainable=lambda s: (s.sigma, s.rho, s.beta),
        max_epochs=8, checkpoint=sys.argv[2], callbacks=[callback], progress=False,
        solver=ceemx.Alternating(learner=ceemx.LMLearner()),  # fit_a's (the exact M-step)
    )
    print("FINISHED", flush=True)
    """
)


def _strict_json(path):
    def reject(name):
        raise ValueError(f"{path} is not valid JSON: it contains {name}")

    with open(path) as f:
        return json.load(f, parse_constant=reject)


@pytest.mark.slow  # a fresh process compiles everything again
def test_kill_and_resume_matches_uninterrupted_run(prob, tmp_path):
    np.savez(
        tmp_path / "problem.npz", start=START, C=np.asarray(prob.C), y=np.asarray(prob.data.y),
        x_init=np.asarray(prob.x_init),
    )  # fmt: skip
    (tmp_path / "run.py").write_text(_SCRIPT)
    ckpt = tmp_path / "ckpt"
    proc = subprocess.run(
        [sys.executable, str(tmp_path / "run.py"), str(tmp_path / "problem.npz"), str(ckpt)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
    assert proc.stdout.splitlines() == [f"EPOCH {k}" for k in (1, 2, 3, 4)], proc.stdout
    # The killed run left the checkpoint of epoch 3, and nothing else but its lock file (no
    # longer held: the kernel released it; the resume below takes it over and removes it).
    assert sorted(os.listdir(ckpt)) == [".lock", "latest.json", "state-3.eqx"]
    meta = _strict_json(ckpt / "latest.json")
    assert meta["epoch"] == 3 and meta["state"] == "state-3.eqx" and len(meta["history"]) == 3

    # Resume in this process with the same call.
    resumed = fit_a(prob, max_epochs=8, checkpoint=str(ckpt))
    full = fit_a(prob, max_epochs=8)
    assert resumed.epochs == full.epochs == 8
    assert [h["epoch"] for h in resumed.history] == list(range(1, 9))
    np.testing.assert_allclose(theta_of(resumed.system), theta_of(full.system), rtol=1e-12, atol=0)
    np.testing.assert_allclose(resumed.states, full.states, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(resumed.history_array("J"), full.history_array("J"), rtol=1e-12)
    np.testing.assert_allclose(resumed.initial_J, full.initial_J, rtol=1e-12)
    assert resumed.converged == full.converged
    # The epochs run by the killed process are those of the uninterrupted run.
    J_killed = [h["J"] for h in meta["history"]]
    np.testing.assert_allclose(J_killed, full.history_array("J")[:3], rtol=1e-12)

    assert sorted(os.listdir(ckpt)) == ["latest.json", "state-8.eqx"]
    meta = _strict_json(ckpt / "latest.json")
    assert meta["epoch"] == 8 and len(meta["history"]) == 8

    # Resuming a finished run returns it without further epochs.
    again = fit_a(prob, max_epochs=8, checkpoint=str(ckpt))
    assert again.epochs == 8
    np.testing.assert_array_equal(theta_of(again.system), theta_of(resumed.system))
    np.testing.assert_array_equal(again.states, resumed.states)


# --------------------------------------------------------------------------------------------------
# Initial states
# --------------------------------------------------------------------------------------------------


def test_from_observations_inverts_a_full_rank_observation():
    rng = np.random.default_rng(0)
    n = 3
    A = rng.standard_normal((n, n))
    A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))
    C = rng.standard_normal((n, n))
    system = LinearSystem(jnp.asarray(A), jnp.asarray(C), process_noise=0.1, obs_noise=0.2)
    x1 = jnp.asarray(rng.standard_normal((2, n)))
    xs, data = simulate(system, jax.random.PRNGKey(0), x1, 20, process_noise=True, obs_noise=False)
    x_exact = ceemx.identification.initialize.from_observations(system, data, ridge=0.0)
    np.testing.assert_allclose(x_exact, xs, rtol=1e-10, atol=1e-10)
    # The default ridge is tiny: still very close.
    x_ridge = ceemx.identification.initialize.from_observations(system, data)
    np.testing.assert_allclose(x_ridge, xs, rtol=1e-3, atol=1e-3 * float(np.max(np.abs(xs))))


def test_rollout_equals_noise_free_simulation(prob):
    xs, data = simulate(
        prob.true, jax.random.PRNGKey(1), prob.x1, T, process_noise=False, obs_noise=False
    )
    x = ceemx.identification.initialize.rollout(prob.true, data, prob.x1)
    np.testing.assert_allclose(x, xs, rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(x[:, 0], prob.x1)


@pytest.mark.slow
def test_fit_without_initial_states(prob):
    res = ceemx.fit(
        prob.start, prob.data, trainable=where_theta, max_epochs=3, solver=ceemx.Alternating()
    )
    x0 = ceemx.identification.initialize.warm_start(prob.start, prob.data)  # the default start
    assert res.epochs == 3
    np.testing.assert_allclose(
        res.initial_J, float(np.sum(log_joint(prob.start, x0, prob.data))), rtol=1e-12
    )
    J = res.history_array("J")
    assert np.all(np.isfinite(J)) and J[0] > res.initial_J
    assert np.all(np.diff(J) >= -1e-9 * np.abs(J[1:]))


# --------------------------------------------------------------------------------------------------
# Precision and input validation
# --------------------------------------------------------------------------------------------------


def _float32_problem(prob):
    start = CoupledLorenz(
        jnp.asarray(START[:1], jnp.float32), jnp.asarray(START[1:2], jnp.float32),
        jnp.asarray(START[2:], jnp.float32), jnp.asarray(prob.C, jnp.float32),
        process_noise=ceemx.DiagonalGaussian(np.float32(0.01), 3),
        obs_noise=ceemx.DiagonalGaussian(np.float32(0.01), 2),
    )  # fmt: skip
    data = ceemx.Trajectories(prob.data.y.astype(jnp.float32))
    return start, data, prob.x_init.astype(jnp.float32)


def test_float32_fit_warns(prob):
    start, data, x_init = _float32_problem(prob)
    with pytest.warns(UserWarning, match="float32") as record:
        res = ceemx.fit(
            start, data, x_init, trainable=where_theta, max_epochs=0, solver=ceemx.Alternating()
        )
    # The warning points at the caller, not into ceemx.
    assert any(w.filename == __file__ for w in record if "float32" in str(w.message)), [
        w.filename for w in record
    ]
    assert res.states.dtype == jnp.float32


@pytest.mark.slow
def test_float32_fit_runs_in_float32(prob):
    start, data, x_init = _float32_problem(prob)
    with pytest.warns(UserWarning, match="float32"):
        res = ceemx.fit(
            start, data, x_init, trainable=where_theta, max_epochs=1,
            solver=ceemx.Alternating(), **NO_NOISE_CHECK,
        )  # fmt: skip
    assert res.epochs == 1
    assert res.states.dtype == jnp.float32
    assert res.system.sigma.dtype == jnp.float32
    assert np.isfinite(res.history[0]["J"]) and res.history[0]["J"] > res.initial_J


def test_float64_fit_does_not_warn(prob):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_a(prob, max_epochs=0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"x_init": "short"}, "x_init"),
        ({"x_init": "nan"}, "x_init"),
        ({"max_epochs": -1}, "max_epochs"),
    ],
    ids=["x_init_shape", "x_init_nan", "max_epochs"],
)
def test_bad_inputs_raise_value_error(prob, kwargs, match):
    kwargs = dict(kwargs)
    x_init = prob.x_init
    if kwargs.get("x_init") == "short":
        kwargs["x_init"] = x_init[:, :-1]
    elif kwargs.get("x_init") == "nan":
        kwargs["x_init"] = x_init.at[1, 5, 2].set(jnp.nan)
    else:
        kwargs["x_init"] = x_init
    with pytest.raises(ValueError, match=match):
        ceemx.fit(prob.start, prob.data, trainable=where_theta, **kwargs)


def test_bad_solver_options_raise_before_compute():
    with pytest.raises(ValueError, match="rho_theta"):
        ceemx.Alternating(rho_theta=-1.0)
    with pytest.raises(ValueError, match="rho_x"):
        ceemx.JointLM(rho_x=-1.0)
    with pytest.raises(ValueError, match="linear_solver"):
        ceemx.JointLM(linear_solver="lu")


def test_bad_solver_and_max_epochs_types(prob):
    with pytest.raises(TypeError, match="solver"):
        ceemx.fit(prob.start, prob.data, prob.x_init, solver="joint")
    with pytest.raises(TypeError, match="max_epochs"):
        ceemx.fit(prob.start, prob.data, prob.x_init, max_epochs="3")


def test_blas_limit_from_several_threads_leaves_nothing_limited():
    """Blocks in two threads, left in the order they were entered: one BLAS thread inside the
    first (threadpoolctl lets one Python thread at a time set OpenBLAS's process-wide limit), the
    libraries' own setting back after both, whatever the order."""
    import threading

    from ceemx.infra.runtime import blas_threads

    entered, leave_a, left_a, leave_b = (threading.Event() for _ in range(4))
    seen = {}

    def a():
        with blas_threads():
            seen["a"] = max(_blas_threads())
            entered.set()
            leave_a.wait(10)
        left_a.set()

    def b():
        entered.wait(10)
        with blas_threads():
            leave_a.set()
            left_a.wait(10)
            leave_b.wait(10)

    before = _blas_threads()
    threads = [threading.Thread(target=f) for f in (a, b)]
    for t in threads:
        t.start()
    left_a.wait(10)
    leave_b.set()
    for t in threads:
        t.join(10)
    assert seen["a"] == 1 and _blas_threads() == before
