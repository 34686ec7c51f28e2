"""Regression tests of the validation audit: mixed precision, casting, clear errors, bad options.

Each test failed before its fix (a crash inside ``lax.while_loop``, NumPy's own error, a value
silently changed, or an option accepted).
"""

import re
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.data.checks import check_inputs, promote_inputs
from ceemx.evaluation.initial_state import estimate_initial_state
from ceemx.evaluation.metrics import benchmark_score
from ceemx.models.noise import CholeskyGaussian, DiagonalGaussian
from ceemx.systems import LinearSystem
from ceemx.systems.lorenz import CoupledLorenz

B, T, M, N = 2, 6, 2, 2


def raises(exc, match):
    return pytest.raises(exc, match=re.escape(match))


def system(dtype=jnp.float64, C=None):
    A = jnp.asarray([[0.9, 0.1], [0.0, 0.8]], dtype)
    C = jnp.asarray([[1.0, 0.0], [0.5, 1.0]] if C is None else C, dtype)
    return LinearSystem(A, C, process_noise=0.1, obs_noise=0.2)


def observations(dtype=np.float64):
    return np.random.default_rng(0).standard_normal((B, T, M)).astype(dtype)


# --- 4. mixed precision: promoted once to the system's dtype ----------------------------------


@pytest.mark.parametrize(
    "sys_dtype, data_dtype, x_dtype",
    [
        (jnp.float64, np.float32, np.float32),
        (jnp.float64, np.float32, np.float64),
        # A second oracle (≈ 3 s: the smoother compiled in float32): that smooth casts through
        # promote_inputs is checked by the float64-system cases, the cast down to a float32
        # system by test_promote_inputs_casts_everything_once.
        pytest.param(jnp.float32, np.float64, np.float64, marks=pytest.mark.slow),
        (jnp.float64, np.float16, np.float16),
    ],
    ids=["f32-data", "f32-data-f64-x", "f32-system", "f16-data"],
)
def test_smooth_mixed_precision_promotes_to_system_dtype(sys_dtype, data_dtype, x_dtype):
    data = ceemx.Trajectories(observations(data_dtype))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the float32 accuracy warning
        sol = ceemx.smooth(system(sys_dtype), data, np.zeros((B, T, N), x_dtype))
    assert sol.states.dtype == sys_dtype and sol.objective.dtype == sys_dtype
    assert np.all(np.isfinite(np.asarray(sol.states)))


def test_smooth_float16_system_is_refused():
    data = ceemx.Trajectories(observations(np.float16))
    with raises(ValueError, "the system's parameters have dtype float16"):
        ceemx.smooth(system(jnp.float16), data, np.zeros((B, T, N)))


def test_promote_inputs_casts_everything_once():
    sys32 = LinearSystem(
        jnp.eye(N, dtype=jnp.float32),
        jnp.eye(N, dtype=jnp.float32),
        process_noise=jnp.asarray([0.1, 0.1]),  # strongly typed float64 noise
    )
    data = ceemx.Trajectories(observations(), np.ones((B, T, 1)))
    s, d, x = promote_inputs(sys32, data, np.zeros((B, T, N)))
    leaves = [a for a in __import__("jax").tree_util.tree_leaves(s) if hasattr(a, "dtype")]
    assert all(a.dtype == jnp.float32 for a in leaves if jnp.issubdtype(a.dtype, jnp.floating))
    assert d.y.dtype == d.u.dtype == x.dtype == jnp.float32
    same_sys, same_data, _ = promote_inputs(system(), ceemx.Trajectories(observations()), None)
    assert same_data.y.dtype == jnp.float64 and same_sys.A.dtype == jnp.float64


def test_promote_overflow_names_the_argument():
    data = ceemx.Trajectories(np.full((B, T, M), 1e300))
    with raises(ValueError, "`data.y` has the value 1e+300 at index [0, 0, 0], which overflows"):
        promote_inputs(system(jnp.float32), data)
    with raises(ValueError, "`x_init` has the value 1e+300"):
        ceemx.smooth(
            system(jnp.float32),
            ceemx.Trajectories(observations(np.float32)),
            np.full((B, T, N), 1e300),
        )


def test_check_inputs_refuses_mixed_dtypes_naming_both():
    data = ceemx.Trajectories(observations(np.float32))
    with raises(ValueError, "`data.y` has dtype float32 but the system's parameters have dtype"):
        check_inputs(system(), data)


@pytest.mark.parametrize(
    "sys_dtype, data_dtype",
    [pytest.param(jnp.float32, np.float64, marks=pytest.mark.slow), (jnp.float64, np.float32)],
)
@pytest.mark.parametrize(
    "solver",
    [pytest.param(ceemx.JointLM(), marks=pytest.mark.slow), ceemx.Alternating()],
    ids=["joint", "alt"],
)  # the joint cases under slow (≈ 2 s of compilation each): the promotion is the driver's
def test_fit_mixed_precision_is_clear(sys_dtype, data_dtype, solver):
    sys, data = system(sys_dtype), ceemx.Trajectories(observations(data_dtype))
    x = np.zeros((B, T, N), data_dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            result = ceemx.fit(sys, data, x, solver=solver, max_epochs=1)
        except ValueError as err:  # until fit promotes: refused naming both dtypes
            assert "float32" in str(err) and "float64" in str(err)
        else:  # fit promotes (driver calls promote_inputs)
            assert result.states.dtype == sys_dtype
        # what the driver does: promote, then fit, in the system's dtype
        sys, data, x = promote_inputs(sys, data, x)
        result = ceemx.fit(sys, data, x, solver=solver, max_epochs=1)
    assert result.states.dtype == sys_dtype
    assert np.all(np.isfinite(np.asarray(result.states)))


def test_learn_float32_warns_and_promotes():
    data = ceemx.Trajectories(observations(np.float32))
    with pytest.warns(UserWarning, match="identifying in float32"):
        new, _, _ = ceemx.learn(system(jnp.float32), np.zeros((B, T, N), np.float32), data)
    assert new.A.dtype == jnp.float32
    # The learner of ceemx.Alternating: learn then reuses the program compiled by
    # test_fit_mixed_precision_is_clear[alt-float64-float32] (the same shapes and dtypes).
    learner = ceemx.LMLearner(max_accepted=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # float64 system: promoted, no warning
        new, _, _ = ceemx.learn(system(), np.zeros((B, T, N), np.float32), data, learner=learner)
    assert new.A.dtype == jnp.float64


def test_learn_validates_states_and_rho_theta():
    data = ceemx.Trajectories(observations())
    with raises(ValueError, "`states` must have shape (B, T, n)"):
        ceemx.learn(system(), np.zeros((B, T + 1, N)), data)
    with raises(ValueError, "`states` has a non-finite value at index [0, 0, 0]"):
        ceemx.learn(system(), np.full((B, T, N), np.nan), data)
    for bad in (np.nan, -1.0, np.inf):
        with raises(ValueError, "`rho_theta` must be finite and >= 0"):
            ceemx.learn(system(), np.zeros((B, T, N)), data, rho_theta=bad)


# --- 5. Trajectories: cast first, then check ------------------------------------------------


def test_trajectories_overflow_on_cast_is_an_error():
    y = observations(np.float32)
    with raises(ValueError, "`u` has the value 1e+300 at index [0, 0, 0], which overflows float32"):
        ceemx.Trajectories(y, np.full((B, T, 1), 1e300))
    # masked entries may hold anything
    big = observations()
    big[0, 1, 0] = 1e300
    mask = np.ones((B, T, M), bool)
    mask[0, 1, 0] = False
    data = ceemx.Trajectories(big, mask=mask)
    assert float(data.y[0, 1, 0]) == 0.0


def test_trajectories_huge_float64_kept_under_x64():
    y = observations()
    y[1, 2, 1] = 1e300
    assert float(ceemx.Trajectories(y).y[1, 2, 1]) == 1e300


def test_trajectories_refuses_complex_u():
    with raises(TypeError, "`u` must be real; got complex dtype complex128"):
        ceemx.Trajectories(observations(), np.ones((B, T, 1)) * (1 + 1j))
    with raises(TypeError, "`y` must be real; got complex dtype complex128"):
        ceemx.Trajectories(observations() + 0j)


def test_trajectories_refuses_ragged_and_strings():
    with raises(ValueError, "`y` must be a rectangular array; got a ragged sequence"):
        ceemx.Trajectories([[[1.0], [2.0]], [[1.0]]])
    with raises(TypeError, "`u` must be a numeric array; got dtype <U3"):
        ceemx.Trajectories(observations(), "abc")
    with raises(ValueError, "`mask` must be a rectangular array"):
        ceemx.Trajectories(observations(), mask=[[True] * T, [True]])
    with raises(ValueError, "`y` must be a rectangular array"):
        ceemx.Trajectories.from_arrays([[1.0, 2.0], [1.0]])


# --- 6. clear errors instead of obscure ones ---------------------------------------------------


def lorenz(**kw):
    return CoupledLorenz(10.0, 28.0, 8 / 3, np.eye(3), dt=kw.pop("dt", 0.04), **kw)


def test_system_noise_and_prior_sizes():
    with raises(ValueError, "`system.process_noise.scale` must be a scalar or have shape (3,)"):
        lorenz(process_noise=jnp.ones(5))
    with raises(ValueError, "`system.obs_noise` has dimension 2 but the system's obs_dim is 3"):
        lorenz(obs_noise=CholeskyGaussian(jnp.eye(2)))
    with raises(ValueError, "`system.initial_prior.mean` must have shape (state_dim,) = (3,)"):
        lorenz(initial_prior=ceemx.GaussianPrior(jnp.ones(2), DiagonalGaussian(jnp.ones(3), 3)))


@pytest.mark.parametrize("trainable", [False, lambda s: ()], ids=["false", "empty"])
def test_trainable_selecting_nothing(trainable):
    data = ceemx.Trajectories(observations())
    with raises(ValueError, "`trainable` selects no parameter to learn"):
        ceemx.fit(system(), data, np.zeros((B, T, N)), trainable=trainable, max_epochs=1)
    with raises(ValueError, "`trainable` selects no parameter to learn"):
        ceemx.learn(system(), np.zeros((B, T, N)), data, trainable=trainable)


@pytest.mark.parametrize("bad", ["3", float("nan"), 2.0, True])
def test_max_epochs_type(bad):
    data = ceemx.Trajectories(observations())
    with raises(TypeError, "`max_epochs` must be an int"):
        ceemx.fit(system(), data, np.zeros((B, T, N)), max_epochs=bad)


def test_joint_linear_solver_typo():
    with raises(ValueError, "`linear_solver` must be 'auto', 'dense' or 'cg'; got 'dnse'"):
        ceemx.JointLM(linear_solver="dnse")


def test_coupled_lorenz_from_lists():
    s = CoupledLorenz([10.0], [28.0], [8 / 3], [[1.0, 0.0, 0.0]], H=[[0.0] * 3] * 3, dt=0.04)
    assert s.C.shape == (1, 3) and s.H.shape == (3, 3)
    assert all(jnp.issubdtype(a.dtype, jnp.floating) for a in (s.sigma, s.C, s.H))
    s = CoupledLorenz([10, 9], [28, 28], [3, 3], [[1] * 6])  # integers promoted
    assert s.C.dtype == s.sigma.dtype and jnp.issubdtype(s.C.dtype, jnp.floating)
    with raises(TypeError, "`C` must be real"):
        CoupledLorenz(10.0, 28.0, 8 / 3, np.eye(3) + 0j)


# --- 7. invalid options refused --------------------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0])
@pytest.mark.parametrize(
    "make",
    [
        lambda v: ceemx.Alternating(rho_theta=v),
        lambda v: ceemx.JointLM(rho_theta=v),
        lambda v: ceemx.JointLM(rho_x=v),
        lambda v: ceemx.LMSmoother(rho_x=v),
        lambda v: ceemx.LMSmoother(rtol=v),
        lambda v: ceemx.LMSmoother(damping=v),
    ],
    ids=["alt-rho_theta", "joint-rho_theta", "joint-rho_x", "lm-rho_x", "lm-rtol", "lm-damping"],
)
def test_options_must_be_finite_nonnegative(make, bad):
    with pytest.raises(ValueError, match="must be finite and >=? 0"):  # damping: > 0
        make(bad)


def test_smoother_max_steps():
    with raises(ValueError, "`max_steps` must be an integer >= 0"):
        ceemx.LMSmoother(max_steps=-1)
    with raises(TypeError, "`solver` must be a ceemx.LMSmoother"):
        ceemx.smooth(system(), ceemx.Trajectories(observations()), np.zeros((B, T, N)), "lm")


@pytest.mark.parametrize("dt", [-0.04, 0.0, np.nan, np.inf])
def test_continuous_dt(dt):
    with raises(ValueError, "`system.dt` must be a positive finite number"):
        lorenz(dt=dt)


def test_rank_deficient_observation_warns():
    data = ceemx.Trajectories(observations())
    with pytest.warns(UserWarning, match="observation matrix C .* has rank 1"):
        ceemx.smooth(system(C=[[1.0, 0.0], [2.0, 0.0]]), data, np.zeros((B, T, N)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ceemx.smooth(system(), data, np.zeros((B, T, N)))


# --- the input boundary: one validation pass and one fit problem per entry-point call ----------


@pytest.fixture
def counted(monkeypatch):
    """Count the validation passes (``ceemx.data.checks._validate``, which every entry point
    reaches through ``prepare``) and the ``FitProblem.create`` calls."""
    from ceemx.data import checks
    from ceemx.identification.problem import FitProblem

    calls = {"validate": 0, "create": 0}
    validate, create = checks._validate, FitProblem.create.__func__

    def counting_validate(*args, **kwargs):
        calls["validate"] += 1
        return validate(*args, **kwargs)

    def counting_create(cls, *args, **kwargs):
        calls["create"] += 1
        return create(cls, *args, **kwargs)

    monkeypatch.setattr(checks, "_validate", counting_validate)
    monkeypatch.setattr(FitProblem, "create", classmethod(counting_create))
    return calls


@pytest.mark.parametrize("solver", [ceemx.Alternating, ceemx.JointLM])
def test_fit_validates_once_and_builds_its_problem_once(counted, solver):
    """The warm start, the solver's refusals, the compile thread and the exclusion of an outlier
    trajectory reuse the inputs and the problem of the one ``prepare`` and ``FitProblem.create``."""
    # an outlier record: the health test excludes it (a sub-problem, not a new one), leaving B
    # records: the fit's programs are those test_fit_mixed_precision_is_clear compiled
    y = np.random.default_rng(1).standard_normal((B + 1, T, M))
    y[B] *= 1e3
    with pytest.warns(UserWarning, match="excluded from the fit"):
        result = ceemx.fit(
            system(), ceemx.Trajectories(y), solver=solver(), max_epochs=2, diagnose=False
        )
    assert result.excluded == (B,)
    assert counted == {"validate": 1, "create": 1}


def test_entry_points_validate_once(counted):
    data = ceemx.Trajectories(observations())
    x = np.zeros((B, T, N))
    ceemx.smooth(system(), data, x)
    ceemx.learn(system(), x, data)
    ceemx.warm_start(system(), data)
    assert counted["validate"] == 3


# --- one dtype rule for every entry point -----------------------------------------------------


def linear(a, b=1.0):
    one = np.ones((1, 1))
    return LinearSystem(a * one, one, b * one, 0 * one, process_noise=0.1, obs_noise=0.1)


RECORD = ceemx.Trajectories(
    np.random.default_rng(1).standard_normal((2, 40, 1)),
    np.random.default_rng(2).standard_normal((2, 40, 1)),
)
F32 = ceemx.Trajectories(np.asarray(RECORD.y, np.float32), np.asarray(RECORD.u, np.float32))


def prior32():
    return ceemx.GaussianPrior(
        jnp.zeros(1, jnp.float32), ceemx.DiagonalGaussian(jnp.ones((), jnp.float32), 1)
    )


@pytest.mark.parametrize(
    "entry",
    [
        lambda s, d: ceemx.inference.ekf.ekf(s, d, initial=prior32()).predicted_obs,
        lambda s, d: ceemx.particle_filter(s, d, n_particles=8, initial=prior32()).log_likelihood,
        lambda s, d: estimate_initial_state(s, d, 4),
        lambda s, d: benchmark_score(s, d, 4).rmse,
        lambda s, d: benchmark_score(s, d, 4, x1=np.zeros((2, 1), np.float32)).y_sim,
        lambda s, d: ceemx.evaluation.simulation.predict_k_step(s, d, 2),
    ],
    ids=[
        "ekf",
        "particle_filter",
        "estimate_initial_state",
        "benchmark_score",
        "score-x1",
        "k-step",
    ],
)
def test_every_entry_point_promotes_as_fit_and_smooth(entry):
    """float32 data (and prior, x1) with a float64 system: these refused what fit and smooth
    promote ("the system's parameters are float64 but `data.y` is float32"); now the data are
    cast to the system's dtype, and the answer is the one of float64 data, in float64."""
    system = linear(0.9)
    out = entry(system, F32)
    assert out.dtype == jnp.float64
    same = entry(system, ceemx.Trajectories(np.asarray(F32.y, np.float64), np.asarray(F32.u)))
    np.testing.assert_array_equal(np.asarray(out), np.asarray(same))


def test_free_run_returns_the_systems_dtype():
    """It returned x1's dtype: float32 states from a float64 system (and the reverse)."""
    xs, ys = ceemx.free_run(linear(0.9), np.ones((2, 1), np.float32), np.ones((2, 5, 1)))
    assert xs.dtype == ys.dtype == jnp.float64
    one = np.ones((1, 1), np.float32)
    system32 = LinearSystem(0.5 * one, one, one, 0 * one, process_noise=0.1, obs_noise=0.1)
    xs, ys = ceemx.free_run(system32, np.ones((1,)), np.ones((5, 1)))
    assert xs.dtype == ys.dtype == jnp.float32
