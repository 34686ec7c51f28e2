"""Post-fit analysis and evaluation: defects that used to pass silently or crash.

- ``FitResult.diagnostics()`` on systems without inputs, on fits whose trajectories failed, on
  records of different lengths (the padding left out of the statistics); verdicts of tests that
  were not run are ``None``, never ``True``.
- ``free_run`` and ``simulate`` refuse the model-output bugs ``fit`` and ``smooth`` refuse.
- ``benchmark_score`` on a constant test output; identifiability with a negative parameter and
  a bounded message; ``EarlyStopping.restore`` with another fit's result; initial states outside
  a hybrid's bounds.

One small linear-Gaussian model family (n = 2, m = 1, strongly typed float64: one program per
shape for every test that uses it).
"""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.analysis.diagnostics import residual_diagnostics
from ceemx.identification.analysis.noise_estimate import residual_moments

jax.config.update("jax_enable_x64", True)

A = np.array([[0.95, 0.1], [-0.1, 0.9]])
B_IN = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0]])
Q_STD, R_STD = 0.1, 0.05


def f64(v):
    return jnp.asarray(v, jnp.float64)


def linear(a=A, inputs=True, q_std=Q_STD):
    """The model, with one input or none (strong float64 leaves: one program per shape)."""
    return ceemx.systems.LinearSystem(
        f64(a),
        f64(C),
        f64(B_IN) if inputs else None,
        process_noise=f64(q_std),
        obs_noise=f64(R_STD),
    )


def record(system, T, B=2, seed=0):
    """(states, data) simulated from ``system``: a piecewise-constant input when it takes one."""
    u = None
    if system.input_dim:
        steps = jax.random.normal(jax.random.PRNGKey(100 + seed), (B, T // 5 + 1, 1))
        u = jnp.repeat(steps, 5, axis=1)[:, :T]
    return ceemx.simulate(system, jax.random.PRNGKey(seed), jnp.zeros((B, 2)), T, u)


# --------------------------------------------------------------------------------------------
# FitResult.diagnostics()
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def no_input_fit():
    """A converged JointLM result of the model without inputs (A trainable), two trajectories,
    at the simulated states, as ``fit`` returns it: diagnostics read only the end point, and
    building it compiles no fit."""
    from ceemx.identification.problem import FitProblem
    from ceemx.lib.results import RESULTS, select

    system = linear(inputs=False)
    x, data = record(system, 40)
    problem, theta = FitProblem.create(system, data, trainable=lambda s: s.A)
    status = select(jnp.ones((2,), bool), RESULTS.successful, RESULTS.nonfinite)
    res = ceemx.FitResult(
        system, x, status, [], True, ceemx.JointLM(), 0.0,
        problem=problem, theta=theta, weights=f64([1.0, 1.0]),
    )  # fmt: skip
    return res, data


def test_diagnostics_of_a_fit_without_inputs(no_input_fit):
    """p = 0 used to fail: "cannot reshape array of size 0 into shape (0)"."""
    res, _ = no_input_fit
    diag = res.diagnostics(lags=5, estimate=False)
    assert diag.cross_correlation.shape == (1, 0, 11) and diag.independent.shape == (1, 0)
    assert np.isfinite(diag.nis).all() and diag.white[0] is not None
    assert "input" not in diag.summary().split("one-step prediction errors")[1].split("\n")[1]


def test_diagnostics_leave_out_failed_trajectories_and_refuse_when_all_failed(no_input_fit):
    """Weights 0 mark trajectories a fit gave up on: left out; all of them: a clear error.

    With every trajectory failed it used to fail with "need at least one array to stack".
    """
    res, data = no_input_fit
    one = dataclasses.replace(res, weights=f64([0.0, 1.0]))
    diag = one.diagnostics(lags=5, estimate=False)
    alone = residual_diagnostics(res.system, data[1], res.states[1:], lags=5, estimate=False)
    np.testing.assert_allclose(diag.nis, alone.nis, rtol=1e-12)
    assert diag.counts[0] == 40
    none = dataclasses.replace(res, weights=f64([0.0, 0.0]))
    with pytest.raises(ValueError, match="no trajectory of this fit has a usable end point"):
        none.diagnostics()


@pytest.fixture(scope="module")
def with_input():
    """The model with one input, (states, data) of two records of 60 steps, and the same with
    the second record cut to 35 steps (padded to 60, the padding masked, its inputs held)."""
    system = linear()
    x, data = record(system, 60)
    mask = np.ones((2, 60, 1), bool)
    mask[1, 35:] = False
    u = np.asarray(data.u).copy()
    u[1, 35:] = u[1, 34]
    padded = ceemx.Trajectories(np.asarray(data.y), u, mask)
    return system, x, data, padded


def test_records_of_different_lengths_leave_their_padding_out(with_input):
    """Padding masked after a record's end adds nothing to the noise ratios.

    Two records of 60 and 35 steps (the second padded to 60, its inputs held) under a process
    noise assumed 10× too loose: the realised / assumed variance must be what the two records
    give on their own (their residual moments pooled). The padded steps' posterior is the prior,
    so each used to add exactly the assumed Q and pull the ratio towards 1 (on an unstable
    model its spread overflowed, and the record was dropped).
    """
    _, x, data, padded = with_input
    loose = linear(q_std=10 * Q_STD)
    diag = residual_diagnostics(loose, padded, x, lags=5, estimate=False)
    parts = [
        residual_moments(loose, data[0], x[:1]),
        residual_moments(loose, data[1].head(35), x[1:, :35]),
    ]
    S_w = sum(np.asarray(p.moments["dyn"]) for p in parts)
    S_w = S_w / sum(float(p.moments["dyn_count"]) for p in parts)
    want = np.diagonal(S_w) / (10 * Q_STD) ** 2
    np.testing.assert_allclose(diag.noise_ratios["process_noise"], want, rtol=1e-6)
    assert want[0] < 0.2  # far below 1 (the observed state): what the padding hid
    assert diag.counts[0] == 60 + 35


def test_tests_not_run_are_none_not_true(with_input, tmp_path):
    """Errors that are not white: the input and bias tests are not run, and say so.

    ``independent`` and ``unbiased`` used to start True and stay True; the figure titled the
    input panel "(independent)".
    """
    from ceemx.evaluation import plots

    _, x, _, data = with_input  # the padded records: the programs of the test above
    diag = residual_diagnostics(linear(a=0.3 * A), data, x, lags=5, estimate=False)
    assert diag.white[0] is False and diag.nis_ok[0] is not None
    assert diag.independent[0, 0] is None and diag.unbiased[0] is None
    assert not diag.ok and "input and bias tests not run" in diag.summary()
    fig = plots.plot_residual_diagnostics(diag)
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    assert "output 1 and input 1 (not tested)" in titles
    assert not any("(independent)" in t for t in titles)
    good = residual_diagnostics(linear(), data, x, lags=5, estimate=False)
    assert good.white[0] is True and good.independent[0, 0] is True and good.unbiased[0] is True


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        "linear",
        "linear_u",
        "lorenz",
        "coupled_lorenz",
        "neural",
        "neural_u",
        "hybrid",
        "tanks",
        "silverbox",
        "drives",
    ],
)
def test_diagnostics_on_every_built_in_system(name):
    """``FitResult.diagnostics()`` after a one-epoch fit of each built-in system (p = 0 or 1)."""
    system, x1, u = _built_in(name)
    T = 30
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a one-epoch fit: not converged, noise check
        x, data = ceemx.simulate(system, jax.random.PRNGKey(3), x1, T, u)
        res = ceemx.fit(system, data, x, solver=ceemx.JointLM(), max_epochs=1)
        diag = res.diagnostics(lags=5)
    m, p = system.obs_dim, system.input_dim
    assert diag.cross_correlation.shape == (m, p, 11) and diag.independent.shape == (m, p)
    assert np.isfinite(diag.nis).all() and all(v is not None for v in diag.white)
    assert diag.estimated_std is not None and "Residual diagnostics" in diag.summary()


def _built_in(name):
    """(system, x₁ (1, n), inputs (1, T, p) or None) of each built-in system, tiny."""
    S = ceemx.systems
    T = 30
    u = jnp.sin(0.3 * jnp.arange(T, dtype=jnp.float64))[None, :, None]
    key = jax.random.PRNGKey(0)
    if name in ("linear", "linear_u"):
        system = linear(inputs=name == "linear_u")
        return system, jnp.ones((1, 2)), u if name == "linear_u" else None
    if name == "lorenz":
        system = S.CoupledLorenz(
            [10.0], [28.0], [8 / 3], np.eye(3)[:2], process_noise=0.1, obs_noise=0.5
        )
        return system, system.default_state_mean()[None], None
    if name == "coupled_lorenz":
        ones = np.ones(2)
        system = S.CoupledLorenz(
            10 * ones,
            28 * ones,
            8 / 3 * ones,
            np.eye(6)[::2],
            H=0.01 * np.ones((6, 6)),
            process_noise=0.1,
            obs_noise=0.5,
        )
        return system, system.default_state_mean()[None], None
    if name in ("neural", "neural_u"):
        p = 1 if name == "neural_u" else 0
        system = S.NeuralObservationSystem(
            0.9 * np.eye(2),
            np.ones((2, p)),
            np.eye(2)[:1],
            np.zeros((1, p)),
            key=key,
            width=4,
            depth=1,
            process_noise=0.1,
            obs_noise=0.1,
        )
        return system, jnp.ones((1, 2)), u if p else None
    if name == "hybrid":
        physics = linear()
        _, data = ceemx.simulate(physics, key, jnp.ones((1, 2)), T, u)
        system = ceemx.hybrid(physics, data, width=4, depth=1, lower=-10.0)
        return system, jnp.ones((1, 2)), u
    gray = {"tanks": S.CascadedTanks, "silverbox": S.Silverbox, "drives": S.CoupledDrives}[name]
    system = gray.default()
    scale = {"tanks": 5.0, "silverbox": 0.1, "drives": 1.0}[name]
    return system, system.default_state_mean()[None], scale * (1.0 + u)


@pytest.mark.slow
def test_diagnostics_of_a_laplace_fit_whose_every_trajectory_failed():
    """A state neither observed nor pinned: the fit is refused at its start; a fit whose every
    trajectory failed later has no residuals, and diagnostics() says why."""
    unobservable = ceemx.systems.LinearSystem(
        f64(np.diag([0.9, 1.0])), f64(C), process_noise=f64(0.1), obs_noise=f64(0.1)
    )
    x, data = ceemx.simulate(unobservable, jax.random.PRNGKey(0), jnp.ones((2, 2)), 30)
    with (
        pytest.raises(ValueError, match="the fit cannot start: LaplaceEM"),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore")  # the failed E-step is also warned about
        ceemx.fit(unobservable, data, x, solver=ceemx.LaplaceEM(), trainable=lambda s: s.A)
    system = ceemx.systems.LinearSystem(
        f64(np.diag([0.9, 0.8])), f64(np.eye(2)), process_noise=f64(0.1), obs_noise=f64(0.1)
    )
    x, data = ceemx.simulate(system, jax.random.PRNGKey(0), jnp.ones((2, 2)), 30)
    res = ceemx.fit(
        system, data, x, solver=ceemx.LaplaceEM(), trainable=lambda s: s.A, max_epochs=1
    )
    failed = eqx.tree_at(lambda r: r.weights, res, jnp.zeros_like(res.weights))
    with pytest.raises(ValueError, match="no trajectory of this fit has a usable end point"):
        failed.diagnostics()


# --------------------------------------------------------------------------------------------
# free_run and simulate check the model's outputs as fit and smooth do
# --------------------------------------------------------------------------------------------


class Plant(ceemx.AbstractSystem):
    """x⁺ = a·x + u, y = x₁: the base of the faulty models below."""

    a: jax.Array

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.a * x + u[0]

    def observe(self, x, u, t):
        return x[:1]


FAULTS = {  # method: (what it returns instead, the words of the message)
    "observe, wrong shape": ("observe", lambda s, x: x, "must return shape"),
    "observe, a scalar": ("observe", lambda s, x: x[0], "must return shape"),
    "observe, rank 2": ("observe", lambda s, x: x[None, :1], "must return shape"),
    "observe, complex": ("observe", lambda s, x: x[:1] * (1 + 0j), "dtype"),
    "observe, a list": ("observe", lambda s, x: [x[0]], "one array"),
    "observe, a tuple": ("observe", lambda s, x: (x[:1], x[:1]), "one array"),
    "observe, None": ("observe", lambda s, x: None, "one array"),
    "observe, float32": ("observe", lambda s, x: x[:1].astype(jnp.float32), "dtype"),
    "observe, integer": ("observe", lambda s, x: x[:1].astype(jnp.int32), "dtype"),
    "observe, raises": ("observe", lambda s, x: x[5:7] @ x, "failed when called"),
    "dynamics, wrong shape": ("dynamics", lambda s, x: x[:1], "must return shape"),
    "dynamics, rank 2": ("dynamics", lambda s, x: x[None], "must return shape"),
    "dynamics, complex": ("dynamics", lambda s, x: s.a * x * (1 + 0j), "dtype"),
    "dynamics, a list": ("dynamics", lambda s, x: [x[0], x[1]], "one array"),
    "dynamics, float32": ("dynamics", lambda s, x: x.astype(jnp.float32), "dtype"),
}


def faulty(method, returns):
    """A Plant whose ``method`` returns ``returns(self, x)``."""
    cls = type("Faulty", (Plant,), {method: lambda self, x, u, t: returns(self, x)})
    return cls(f64(0.5), process_noise=f64(0.1), obs_noise=f64(0.1))


@pytest.mark.parametrize("entry", ["free_run", "simulate"])
@pytest.mark.parametrize("fault", list(FAULTS))
def test_free_run_and_simulate_name_a_faulty_model_method(fault, entry):
    """The shape and dtype checks of fit and smooth, before any compute.

    free_run used to return a wrong-shaped observe as is, cast a complex dynamics silently and
    fail with an AttributeError on a list; simulate failed inside its scan.
    """
    method, returns, words = FAULTS[fault]
    model = faulty(method, returns)
    x1, u = jnp.ones((1, 2)), jnp.ones((1, 6, 1))
    with pytest.raises(ValueError, match=rf"`system\.{method}`.*{words}"):
        if entry == "free_run":
            ceemx.free_run(model, x1, u)
        else:
            ceemx.simulate(model, jax.random.PRNGKey(0), x1, 6, u)


@pytest.mark.parametrize("method", ["observe", "dynamics"])
def test_a_run_that_turns_nan_names_the_method(method):
    """NaN from the model: free_run warns (the run is returned), simulate refuses; both name it."""
    nan_from = {
        "observe": lambda s, x: jnp.log(x[:1] - 1.5),
        "dynamics": lambda s, x: jnp.sqrt(x - 0.8),
    }
    model = faulty(method, nan_from[method])
    x1, u = jnp.ones((1, 2)), jnp.zeros((1, 6, 1))
    with pytest.warns(UserWarning, match=rf"free_run: the run is not finite: `system\.{method}`"):
        xs, ys = ceemx.free_run(model, x1, u)
    assert not np.isfinite(np.asarray(ys)).all()
    with pytest.raises(ValueError, match=rf"simulation is not finite: `system\.{method}`.*step"):
        ceemx.simulate(model, jax.random.PRNGKey(0), x1, 6, u, process_noise=False)


def test_simulate_casts_the_start_to_the_systems_dtype():
    """float32 or integer start states of a float64 system used to fail inside the scan."""
    system = linear(inputs=False)
    for x0 in (jnp.ones((1, 2), jnp.float32), np.ones((1, 2), int)):
        x, data = ceemx.simulate(system, jax.random.PRNGKey(0), x0, 5)
        assert x.dtype == jnp.float64 and data.y.dtype == jnp.float64
    with pytest.raises(ValueError, match=r"`x0` must have shape \(B, n\) with n = 2"):
        ceemx.simulate(system, jax.random.PRNGKey(0), jnp.ones((1, 3)), 5)
    with pytest.raises(ValueError, match="`x0` has a non-finite value"):
        ceemx.simulate(system, jax.random.PRNGKey(0), jnp.array([[1.0, np.nan]]), 5)


# --------------------------------------------------------------------------------------------
# benchmark_score on a constant output
# --------------------------------------------------------------------------------------------


def test_benchmark_score_of_a_constant_output_is_nan_with_its_status():
    """NRMSE and fit % of an output with no spread: NaN, warned, status constant_output.

    They used to read NRMSE = inf and fit % = −inf under status "converged".
    """
    system = ceemx.systems.LinearSystem(f64([[0.5]]), f64([[1.0], [1.0]]), f64([[1.0]]))
    T = 30
    u = np.sin(0.4 * np.arange(T))[None, :, None]
    _, y = ceemx.free_run(system, f64([[1.0]]), u)
    y = np.asarray(y).copy()
    y[0, :, 1] = 0.1  # the second output constant
    with pytest.warns(UserWarning, match="constant.*record 0 output 2.*NaN"):
        s = ceemx.benchmark_score(system, ceemx.Trajectories(y, u), 5, x1=f64([[1.0]]))
    assert np.isnan(s.nrmse[0, 1]) and np.isnan(s.fit_percent[0, 1])
    assert np.isnan(s.nrmse_overall[0]) and np.isnan(s.fit_percent_overall[0])
    assert s.nrmse[0, 0] == 0.0 and s.fit_percent[0, 0] == 100.0  # the exact output: a score
    np.testing.assert_allclose(s.rmse[0, 1], np.sqrt(np.mean((y[0, 5:, 0] - 0.1) ** 2)))
    assert bool(s.status == ceemx.RESULTS.constant_output)


# --------------------------------------------------------------------------------------------
# Identifiability: negative parameters, bounded messages
# --------------------------------------------------------------------------------------------


class Product(ceemx.AbstractSystem):
    """x⁺ = 0.9·x + a·b·u, y = x: only a·b is determined, whatever the signs."""

    a: jax.Array
    b: jax.Array

    state_dim = 1
    obs_dim = 1
    input_dim = 1

    def dynamics(self, x, u, t):
        return 0.9 * x + self.a * self.b * u

    def observe(self, x, u, t):
        return x


@pytest.mark.parametrize("a, b", [(1.5, 2.0), (1.5, -2.0), (-1.5, -2.0), (-1.5, 2.0)])
def test_identifiability_names_the_product_whatever_the_signs(a, b):
    """S = c·g gᵀ with g = ∇(a·b) = (b, a): the data determine a·b alone.

    With b = −2 it used to read "only a/b is determined": the relative scale used |θ|, so a
    unit of a negative parameter's coordinate divided it by e instead of multiplying.
    """
    from ceemx.identification.analysis.identifiability import analyse
    from ceemx.identification.problem import FitProblem

    system = Product(f64(a), f64(b), process_noise=f64(0.1), obs_noise=f64(0.1))
    data = ceemx.Trajectories(np.zeros((1, 3, 1)), np.zeros((1, 3, 1)))
    problem, theta = FitProblem.create(system, data)
    g = np.array([b, a])
    found = analyse(problem, theta, 1e4 * np.outer(g, g))
    assert found is not None and found.determined == ("a·b",), found
    assert found.exponents == ((("a", 1), ("b", 1)),)


@pytest.mark.slow
def test_identifiability_of_a_fit_with_a_negative_parameter():
    """The fit's own analysis (JointLM, check_identifiability) on the product with b = −2."""
    system = Product(f64(1.5), f64(-2.0), process_noise=f64(0.01), obs_noise=f64(0.01))
    u = jax.random.normal(jax.random.PRNGKey(1), (1, 40, 1))
    x, data = ceemx.simulate(system, jax.random.PRNGKey(0), jnp.zeros((1, 1)), 40, u)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = ceemx.fit(system, data, x, solver=ceemx.JointLM(), max_epochs=3)
    found = res.check_identifiability()
    assert found is not None and found.determined == ("a·b",), found


def test_identifiability_message_of_many_weights_is_bounded():
    """A learned term's weights: the few most involved named, the rest counted.

    A hybrid with 370 parameters used to put every weight and a coefficient per weight and
    direction into one message (12 MB).
    """
    from ceemx.lib.nullspace import MAX_NAMED, describe_null_space

    P, k = 60, 50
    rng = np.random.default_rng(0)
    basis, _ = np.linalg.qr(rng.normal(size=(P, k)))
    names = [f"w[{i}]" for i in range(P)]
    out = describe_null_space(basis, names, np.ones(P, bool), np.ones(P))
    assert len(out.text) < 600, len(out.text)
    assert out.text.startswith(f"{k} directions among {P} parameters (w[")
    assert f"and {P - MAX_NAMED} more) are not determined by the data" in out.text
    assert len(out.undetermined) == P  # the structured record keeps every name
    # Many separate groups: a few sentences, the rest counted.
    blocks = np.zeros((2 * 40, 40))
    for i in range(40):
        blocks[2 * i : 2 * i + 2, i] = [1.0, -1.1]  # not an integer direction: coefficients
    blocks /= np.linalg.norm(blocks, axis=0)
    out = describe_null_space(blocks, [f"p{i}" for i in range(80)], np.ones(80, bool), np.ones(80))
    assert out.text.count("; ") == 5 and "35 more groups of parameters" in out.text


# --------------------------------------------------------------------------------------------
# EarlyStopping: one fit at a time, its own result only
# --------------------------------------------------------------------------------------------


def test_early_stopping_restores_only_the_fit_it_watched(with_input):
    """``restore`` refuses another fit's result; reused in a second fit, it starts over.

    It used to put the first fit's best model into any result, and, reused, return the first
    fit's model for the second fit.
    """
    from ceemx.evaluation.early_stopping import EarlyStopping
    from ceemx.identification.fitting.result import EpochInfo

    truth, x, data, _ = with_input
    worse = linear(a=0.7 * A)
    stop = EarlyStopping(data, n_init=5, patience=3, score_options={"x1": x[:, 0]})

    def fit_by_hand(*systems):
        """The callback's view of a fit whose epochs end at ``systems``; its result."""
        history = []
        for k, system in enumerate(systems, start=1):
            record = {"epoch": k, "J": 0.0}
            stop(EpochInfo(k, system, x, record))
            history.append(record)
        return ceemx.FitResult(systems[-1], x, ceemx.RESULTS.successful, history, False,
                               ceemx.JointLM(), 0.0)  # fmt: skip

    with pytest.raises(ValueError, match="watched no epoch"):
        stop.restore(ceemx.FitResult(worse, x, ceemx.RESULTS.successful, [], False,
                                     ceemx.JointLM(), 0.0))  # fmt: skip
    first = fit_by_hand(worse, truth, worse)
    other = dataclasses.replace(first, history=[{"epoch": k, "J": 0.0} for k in (1, 2, 3)])
    with pytest.raises(ValueError, match="not the fit this EarlyStopping watched"):
        stop.restore(other)
    assert stop.restore(first).system is truth and stop.best_epoch == 2
    second = fit_by_hand(worse, worse)  # a second fit: epochs start again
    assert stop.best_epoch == 1 and [e for e, _ in stop.scores] == [1, 2]
    assert stop.restore(second).system is worse
    with pytest.raises(ValueError, match="not the fit this EarlyStopping watched"):
        stop.restore(first)


# --------------------------------------------------------------------------------------------
# Initial states outside a hybrid model's bounds
# --------------------------------------------------------------------------------------------


@pytest.mark.slow  # the initial-state smoother's compile (≈ 2.5 s)
def test_initial_state_outside_a_hybrids_bounds_is_warned():
    """A hidden state bounded below by 0, data from a start at −2: x̂₁ below the bound, warned.

    It used to be returned without a word (a hidden tank level of −1.04 V on the tanks).
    """
    from ceemx.systems.hybrid import Hybrid

    physics = ceemx.systems.LinearSystem(
        f64([[0.9, 0.3], [0.0, 0.95]]), f64(C), f64(B_IN), process_noise=f64(0.01),
        obs_noise=f64(0.01),
    )  # fmt: skip
    u = jnp.zeros((1, 20, 1))
    _, data = ceemx.simulate(physics, jax.random.PRNGKey(0), f64([[0.0, -2.0]]), 20, u)
    model = Hybrid(physics, lower=f64([-np.inf, 0.0]))  # bounds, no learned term
    with pytest.warns(UserWarning, match=r"outside the model's state bounds.*state 2 of traj"):
        x1 = ceemx.estimate_initial_state(model, data, 10, refine=False, warm_process_noise=None)
    assert float(x1[0, 1]) < 0.0
