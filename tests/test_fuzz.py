"""Property-based fuzzing of the public entry points' validation.

Every generated call is either accepted — and then the result is finite and shaped right — or
rejected with a ``ValueError``/``TypeError`` whose message names the offending argument. Never any
other exception, never NaN returned.

Compiled calls reuse ONE tiny system and ONE data shape (values vary, shapes do not), so JAX
compiles a handful of programs; shapes vary only on validation paths that fail before compute.
Profiles: ``default`` (modest, deadline-free) and ``slow`` (``CEEMX_FUZZ=slow`` or
``HYPOTHESIS_PROFILE=slow``: ten times the examples).
"""

import os
import re
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import ceemx
from ceemx.systems import LinearSystem

_COMMON = dict(deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
settings.register_profile("default", max_examples=100, **_COMMON)
settings.register_profile("slow", max_examples=1000, **_COMMON)
PROFILE = os.environ.get("CEEMX_FUZZ", os.environ.get("HYPOTHESIS_PROFILE", "default"))
settings.load_profile(PROFILE)
SCALE = 10 if PROFILE == "slow" else 1


def examples(n: int):
    """``n`` examples in the default profile (the slow profile runs ten times as many)."""
    return settings(max_examples=n * SCALE)


B, T, M, N = 2, 5, 2, 2

SPECIAL = st.sampled_from([np.nan, np.inf, -np.inf, 1e300, -1e300, 1e39, 0.0, -0.0, 1e-320])
FLOATS = st.one_of(st.floats(-1e3, 1e3, allow_nan=False), SPECIAL)


def names_an_argument(err: Exception, *names: str) -> bool:
    msg = str(err)
    return any(f"`{n}" in msg for n in names) or "system" in msg


def expect_clean(fn, *names):
    """Run ``fn``: a result, or ValueError/TypeError naming one of ``names``; else fail."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return fn()
    except (ValueError, TypeError) as err:
        assert names_an_argument(err, *names), f"message names no argument: {err}"
        return None


# --- Trajectories: pure validation, any shape ------------------------------------------------

DTYPES = st.sampled_from(
    [np.float64, np.float32, np.float16, np.int32, np.bool_, np.complex64, np.uint8]
)


@st.composite
def arrays(draw, ndim_range=(0, 4)):
    dtype = draw(DTYPES)
    shape = draw(hnp.array_shapes(min_dims=ndim_range[0], max_dims=ndim_range[1], max_side=4))
    if np.issubdtype(dtype, np.floating):
        a = draw(hnp.arrays(np.float64, shape, elements=FLOATS))
        with np.errstate(over="ignore"):
            return a.astype(dtype) if draw(st.booleans()) else a
    return draw(hnp.arrays(dtype, shape))


OTHER = st.sampled_from([None, "abc", [[[1.0], [2.0]], [[1.0]]], 3.0, object()])


@examples(340)
@given(
    y=st.one_of(arrays(), OTHER),
    u=st.one_of(st.none(), arrays(), OTHER),
    mask=st.one_of(st.none(), arrays((2, 3)), OTHER),
)
def test_trajectories_any_arguments(y, u, mask):
    data = expect_clean(lambda: ceemx.Trajectories(y, u, mask), "y", "u", "mask")
    if data is None:
        return
    y_np = np.asarray(y)
    assert data.y.shape == y_np.shape and data.mask.shape == y_np.shape
    assert data.u.shape[:2] == y_np.shape[:2]
    assert np.all(np.isfinite(np.asarray(data.y))) and np.all(np.isfinite(np.asarray(data.u)))
    assert data.y.dtype == data.u.dtype and jnp.issubdtype(data.y.dtype, jnp.floating)


@examples(200)
@given(
    values=hnp.arrays(np.float64, (B, T, M), elements=FLOATS),
    masked=hnp.arrays(np.bool_, (B, T, M)),
    u=hnp.arrays(np.float64, (B, T, 1), elements=FLOATS),
    dtype=st.sampled_from([np.float64, np.float32]),
)
def test_trajectories_values_cast_then_checked(values, masked, u, dtype):
    """Right shapes: accepted exactly when every unmasked y and every u is finite in y's dtype."""
    mask = ~masked
    with np.errstate(over="ignore", invalid="ignore"):
        y = values.astype(dtype)
        fits = bool((np.isfinite(y) | ~mask).all() and np.isfinite(u.astype(dtype)).all())
    data = expect_clean(lambda: ceemx.Trajectories(y, u, mask), "y", "u")
    assert (data is not None) == fits
    if data is not None:
        assert np.all(np.isfinite(np.asarray(data.y))) and np.all(np.isfinite(np.asarray(data.u)))
        assert data.y.dtype == data.u.dtype == dtype


# --- smooth: fixed shapes for compiled calls, any shape for validation -----------------------


def tiny_system(dtype=jnp.float64):
    A = jnp.asarray([[0.9, 0.1], [0.0, 0.8]], dtype)
    C = jnp.asarray([[1.0, 0.0], [0.5, 1.0]], dtype)
    return LinearSystem(A, C, process_noise=0.1, obs_noise=0.2)


SYSTEM = tiny_system()
DATA = ceemx.Trajectories(np.random.default_rng(0).standard_normal((B, T, M)))


@examples(150)
@given(x=arrays((1, 4)))
def test_smooth_x_init_any_shape(x):
    sol = expect_clean(lambda: ceemx.smooth(SYSTEM, DATA, x), "x_init")
    if sol is not None:
        assert sol.states.shape == (B, T, N)
        assert np.all(np.isfinite(np.asarray(sol.states)))


NUMBERS = st.one_of(st.floats(-1.0, 10.0, allow_nan=False), SPECIAL)


@examples(150)
@given(
    x=hnp.arrays(np.float64, (B, T, N), elements=st.floats(-5.0, 5.0)),
    rho_x=NUMBERS,
    rtol=NUMBERS,
    damping=NUMBERS,
    xdtype=st.sampled_from([np.float64, np.float32]),
)
def test_smooth_options_and_values(x, rho_x, rtol, damping, xdtype):
    def run():
        solver = ceemx.LMSmoother(rho_x=rho_x, rtol=rtol, damping=damping, max_steps=5)
        return ceemx.smooth(SYSTEM, DATA, x.astype(xdtype), solver)

    sol = expect_clean(run, "rho_x", "rtol", "damping")
    if sol is not None:
        assert sol.states.shape == (B, T, N) and sol.states.dtype == jnp.float64
        assert np.all(np.isfinite(np.asarray(sol.states)))
        assert np.all(np.isfinite(np.asarray(sol.objective)))


# --- fit and learn: cheap options ------------------------------------------------------------

X0 = np.zeros((B, T, N))
TRAINABLE = st.sampled_from(
    [None, False, True, lambda s: s.A, lambda s: s.C, lambda s: (), lambda s: (s.A, s.C)]
)
EPOCHS = st.one_of(st.integers(-2, 2), st.sampled_from(["3", 2.0, np.nan, True, None, np.int64(1)]))


@pytest.mark.slow  # 60 fits (≈ 4 s); option validation is fuzzed without fitting by default
@examples(60)
@given(max_epochs=EPOCHS, rho=NUMBERS, trainable=TRAINABLE, joint=st.booleans())
def test_fit_options(max_epochs, rho, trainable, joint):
    def run():
        solver = ceemx.JointLM(rho_theta=rho) if joint else ceemx.Alternating(rho_theta=rho)
        return ceemx.fit(
            SYSTEM, DATA, X0, solver=solver, max_epochs=max_epochs, trainable=trainable
        )

    result = expect_clean(run, "max_epochs", "rho_theta", "trainable")
    if result is not None:
        assert result.states.shape == (B, T, N)
        assert np.all(np.isfinite(np.asarray(result.states)))
        assert all(np.all(np.isfinite(np.asarray(a))) for a in (result.system.A, result.system.C))


@pytest.mark.slow
@examples(100)
@given(
    states=hnp.arrays(np.float64, (B, T, N), elements=FLOATS),
    rho=NUMBERS,
    trainable=TRAINABLE,
)
def test_learn_arguments(states, rho, trainable):
    out = expect_clean(
        lambda: ceemx.learn(SYSTEM, states, DATA, rho_theta=rho, trainable=trainable),
        "states",
        "rho_theta",
        "trainable",
    )
    if out is not None:
        new, _, _ = out
        assert new.A.shape == (N, N) and np.all(np.isfinite(np.asarray(new.A)))


# --- every option of every solver and learner: pure validation --------------------------------

_NONNEG, _POS_INT, _NONNEG_INT, _FRACTION = "nonneg", "int>=1", "int>=0", "fraction"
OPTIONS = [
    *[
        (cls, name, _NONNEG)
        for cls in (ceemx.Alternating, ceemx.JointLM, ceemx.LaplaceEM, ceemx.ParticleEM)
        for name in ("rtol", "atol")
    ],
    *[
        (cls, "rho_theta", _NONNEG)
        for cls in (ceemx.Alternating, ceemx.JointLM, ceemx.LaplaceEM, ceemx.ParticleEM)
    ],
    *[(ceemx.JointLM, name, _NONNEG) for name in ("rho_x", "damping", "check_rtol", "cg_rtol")],
    (ceemx.JointLM, "max_trials", _POS_INT),
    (ceemx.JointLM, "dense_max_p", _NONNEG_INT),
    (ceemx.ParticleEM, "ess_threshold", _FRACTION),
    *[(ceemx.ParticleEM, name, _POS_INT) for name in ("n_particles", "n_smoothed", "memory")],
    (ceemx.ParticleEM, "burn_in", _NONNEG_INT),
    *[(ceemx.LMSmoother, name, _NONNEG) for name in ("rho_x", "rtol", "atol", "damping")],
    (ceemx.LMSmoother, "max_steps", _NONNEG_INT),
    *[(ceemx.LMLearner, name, _NONNEG) for name in ("rtol", "atol", "damping")],
    (ceemx.LMLearner, "max_steps", _POS_INT),
    (ceemx.LBFGSLearner, "gtol", _NONNEG),
    *[(ceemx.LBFGSLearner, name, _POS_INT) for name in ("max_steps", "memory_size")],
    *[(ceemx.NelderMeadLearner, name, _NONNEG) for name in ("rtol", "atol")],
    (ceemx.NelderMeadLearner, "max_steps", _POS_INT),
]
OPTION_VALUES = st.one_of(
    SPECIAL,
    st.floats(-10.0, 10.0),
    st.integers(-3, 3),
    st.sampled_from([None, "abc", True, False, 1j, [1.0], np.float64(0.5), np.nan]),
)


def _valid(kind: str, value) -> bool | None:
    """Whether ``value`` is valid for ``kind`` (None: either answer is right).

    Where jaxtyping checks the annotations first (``--jaxtyping-packages``, CI's slow run), an int
    for a float option may be refused although ceemx accepts it: left open.
    """
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | float | np.floating):
        return False
    if kind in (_POS_INT, _NONNEG_INT):
        return isinstance(value, int) and value >= (1 if kind == _POS_INT else 0)
    ok = np.isfinite(value) and value >= 0 and (kind != _FRACTION or value <= 1)
    return None if isinstance(value, int) and ok else bool(ok)


@examples(300)
@given(case=st.sampled_from(OPTIONS), value=OPTION_VALUES)
def test_every_option_validated(case, value):
    """Issue 24: no invalid value silently accepted, no valid one refused, the option named."""
    cls, name, kind = case
    valid = _valid(kind, value)
    try:
        cls(**{name: value})
    except (ValueError, TypeError) as err:
        assert f"`{name}`" in str(err) or f"parameter '{name}'" in str(err), str(err)
        assert valid is not True, f"{cls.__name__}({name}={value!r}) refused: {err}"
        return
    assert valid is not False, f"{cls.__name__}({name}={value!r}) silently accepted"


def test_profile_is_registered():
    assert settings().deadline is None
    assert re.fullmatch(r"default|slow", PROFILE)


@pytest.mark.slow
def test_slow_profile_runs_more():
    assert settings.get_profile("slow").max_examples > settings.get_profile("default").max_examples
