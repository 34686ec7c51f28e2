"""Options: every option of every solver, learner and smoother validated on construction, and
``fit``'s and ``learn``'s ``key`` and ``log_prior`` refused before any compute.

Each test failed before its fix (an option accepted). The refusals of ``fit`` compile nothing:
the ``no_compute`` fixture fails a test whose counting model (tests/refusals.py) was traced.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from refusals import DATA, X0, decay, raises

import ceemx
from ceemx.identification.learning.learners import (
    LBFGSLearner,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
)
from ceemx.infra import options

SOLVERS = [ceemx.Alternating, ceemx.JointLM, ceemx.LaplaceEM, ceemx.ParticleEM]
BAD_TOLERANCES = [
    (-1.0, ValueError, "must be finite and >= 0"),
    (np.nan, ValueError, "must be finite and >= 0"),
    (np.inf, ValueError, "must be finite and >= 0"),
    (-np.inf, ValueError, "must be finite and >= 0"),
    ("abc", TypeError, "must be a real number"),
    (None, TypeError, "must be a real number"),
    (True, TypeError, "must be a real number"),
    (1j, TypeError, "must be a real number"),
]


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: s.__name__)
@pytest.mark.parametrize("name", ["rtol", "atol"])
@pytest.mark.parametrize("bad, exc, match", BAD_TOLERANCES, ids=lambda v: repr(v)[:8])
def test_solver_tolerances(solver, name, bad, exc, match):
    with raises(exc, f"`{name}` {match}"):
        solver(**{name: bad})


LEARNER_CASES = [
    (LMLearner, "damping", np.nan, ValueError, "finite and > 0"),
    (LMLearner, "damping", -1.0, ValueError, "finite and > 0"),
    (LMLearner, "rtol", np.inf, ValueError, "finite and >= 0"),
    (LMLearner, "atol", "x", TypeError, "a real number"),
    (LMLearner, "max_steps", -3, ValueError, "an integer >= 1"),
    (LMLearner, "max_steps", 0, ValueError, "an integer >= 1"),
    (LMLearner, "max_steps", 2.5, TypeError, "an integer"),
    (LMLearner, "max_steps", None, TypeError, "an integer"),
    (LBFGSLearner, "gtol", np.nan, ValueError, "finite and >= 0"),
    (LBFGSLearner, "max_steps", -1, ValueError, "an integer >= 1"),
    (LBFGSLearner, "memory_size", 0, ValueError, "an integer >= 1"),
    (NelderMeadLearner, "rtol", -1.0, ValueError, "finite and >= 0"),
    (NelderMeadLearner, "atol", np.nan, ValueError, "finite and >= 0"),
    (NelderMeadLearner, "max_steps", 0, ValueError, "an integer >= 1"),
    (NelderMeadLearner, "max_steps", "many", TypeError, "an integer or None"),
]


@pytest.mark.parametrize(
    "learner, name, bad, exc, match",
    LEARNER_CASES,
    ids=[f"{c[0].__name__}-{c[1]}-{c[2]!r}" for c in LEARNER_CASES],
)
def test_learner_options(learner, name, bad, exc, match):
    with raises(exc, f"`{name}` must be {match}"):
        learner(**{name: bad})


def test_optax_learner_options():
    with raises(TypeError, "`transform` must be an Optax gradient transformation"):
        OptaxLearner(3)  # pyright: ignore[reportArgumentType]
    with raises(ValueError, "`steps` must be an integer >= 1"):
        OptaxLearner(optax.adam(1e-3), steps=-1)
    with raises(ValueError, "`batch_size` must be an integer >= 1"):
        OptaxLearner(optax.adam(1e-3), batch_size=0)
    OptaxLearner(optax.adam(1e-3), steps=1, batch_size=None)  # fine


@pytest.mark.parametrize(
    "make, exc, match",
    [
        (lambda: ceemx.ParticleEM(ess_threshold=None), TypeError, "`ess_threshold` must be a real"),
        (lambda: ceemx.ParticleEM(ess_threshold="a"), TypeError, "`ess_threshold` must be a real"),
        (
            lambda: ceemx.ParticleEM(ess_threshold=1.5),
            ValueError,
            "`ess_threshold` must be a number",
        ),
        (lambda: ceemx.ParticleEM(alpha="a"), TypeError, "`alpha` must be a real number"),
        (lambda: ceemx.ParticleEM(initial=3.0), TypeError, "`initial` must be None or a ceemx"),
        (
            lambda: ceemx.ParticleEM(n_particles=0),
            ValueError,
            "`n_particles` must be an integer >= 1",
        ),
        (lambda: ceemx.LaplaceEM(acceleration="fast"), ValueError, "`acceleration` must be one of"),
        (lambda: ceemx.LaplaceEM(rho_theta="a"), TypeError, "`rho_theta` must be a real number"),
        (lambda: ceemx.LaplaceEM(coarse_start=1), ValueError, "`coarse_start` must be an integer"),
        (lambda: ceemx.LaplaceEM(coarse_start=1e4), TypeError, "`coarse_start` must be an integer"),
        (lambda: ceemx.JointLM(cg_rtol=np.nan), ValueError, "`cg_rtol` must be finite and >= 0"),
        (lambda: ceemx.JointLM(max_trials=0), ValueError, "`max_trials` must be an integer >= 1"),
        (lambda: ceemx.JointLM(cg_max_steps=0), ValueError, "`cg_max_steps` must be an integer"),
        (lambda: ceemx.JointLM(dense_max_p=-1), ValueError, "`dense_max_p` must be an integer"),
        (lambda: ceemx.JointLM(max_theta_step=np.nan), ValueError, "`max_theta_step` must be > 0"),
        (lambda: ceemx.JointLM(check_smoothing=1), TypeError, "`check_smoothing` must be True"),
        (lambda: ceemx.LMSmoother(throw="yes"), TypeError, "`throw` must be True or False"),
        (lambda: ceemx.LMSmoother(max_steps=1.5), TypeError, "`max_steps` must be an integer"),
        (lambda: ceemx.LMSmoother(batch_chunk=0), ValueError, "`batch_chunk` must be an integer"),
    ],
)
def test_other_options(make, exc, match):
    with raises(exc, match):
        make()


@pytest.mark.parametrize(
    "check, args, exc, match",
    [
        (options.check_nonnegative, ("rtol", "abc"), TypeError, "`rtol` must be a real number"),
        (options.check_nonnegative, ("rtol", None), TypeError, "`rtol` must be a real number"),
        (options.check_nonnegative, ("rtol", True), TypeError, "`rtol` must be a real number"),
        (options.check_nonnegative, ("atol", np.nan), ValueError, "`atol` must be finite"),
        (options.check_nonnegative, ("atol", [1.0]), TypeError, "`atol` must be one real number"),
        (options.check_int, ("max_steps", 2.0, 1), TypeError, "`max_steps` must be an integer;"),
        (options.check_int, ("max_steps", True, 1), TypeError, "`max_steps` must be an integer;"),
        (options.check_positive, ("h", 0.0), ValueError, "`h` must be finite and > 0"),
        (options.check_bool, ("throw", 1), TypeError, "`throw` must be True or False"),
        (options.check_choice, ("mode", "b", ("a", None)), ValueError, "`mode` must be one of"),
    ],
)
def test_option_helpers_messages(check, args, exc, match):
    """What users see (in the test session jaxtyping may see a wrong type first)."""
    with pytest.raises(exc, match=re.escape(match)):
        check(*args)


def test_valid_options_still_accepted():
    ceemx.JointLM(max_theta_step=np.inf, cg_max_steps=None, rtol=0.0, atol=1e-3)
    ceemx.ParticleEM(ess_threshold=1.0, rtol=1e-3, alpha=1.0)
    ceemx.LaplaceEM(acceleration=None, rtol=1e-8)
    ceemx.Alternating(learner=LMLearner(max_steps=3, damping=1e-9))
    NelderMeadLearner(max_steps=None)


@pytest.mark.parametrize(
    "key, exc, match",
    [
        ("abc", TypeError, "`key` must be a JAX PRNG key"),
        (3, TypeError, "`key` must be a JAX PRNG key"),
        (np.zeros(2), TypeError, "`key` must be a JAX PRNG key"),
        (jax.random.split(jax.random.key(0), 2), ValueError, "`key` must be a single PRNG key"),
    ],
    ids=["str", "int", "float-array", "batch"],
)
def test_fit_key_refused_before_compute(no_compute, key, exc, match):
    with raises(exc, match):
        ceemx.fit(decay(), DATA, X0, key=key)


def test_learn_key_refused():
    with raises(TypeError, "`key` must be a JAX PRNG key"):
        ceemx.learn(decay(), X0, DATA, key="abc")


@pytest.mark.parametrize(
    "log_prior, exc, match",
    [
        (lambda s: jnp.nan, ValueError, "`log_prior` is nan at the initial system"),
        (lambda s: -jnp.inf, ValueError, "`log_prior` is -inf at the initial system"),
        (lambda s: jnp.log(s.a - 1.0), ValueError, "`log_prior` is nan"),
        (lambda s: jnp.zeros(3), TypeError, "`log_prior` must return a real scalar"),
        (lambda s: "p", TypeError, "`log_prior` must return a real scalar"),
        (3.0, TypeError, "`log_prior` must be a callable"),
    ],
    ids=["nan", "-inf", "outside-support", "vector", "string", "not-callable"],
)
def test_log_prior_checked_at_the_start(no_compute, log_prior, exc, match):
    with raises(exc, match):
        ceemx.fit(decay(), DATA, X0, log_prior=log_prior)
