"""Failure handling: options validated everywhere, no ``converged=True`` on nonsense, no quiet NaN
in evaluation, user model bugs named, checkpoints a resume can trust, one writer per checkpoint
folder, one dtype rule for every entry point.

Each test failed before its fix (an option accepted, a fit that started on a bound or at an
absurd J and reported convergence). Validation tests compile nothing: a counting system records
every trace of its methods, and the refusals must come before the first one.
"""

import errno
import json
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jaxtyping import Array

import ceemx
from ceemx.data.checks import check_inputs
from ceemx.evaluation.initial_state import estimate_initial_state
from ceemx.evaluation.metrics import benchmark_score
from ceemx.identification.learning.learners import (
    LBFGSLearner,
    LMLearner,
    NelderMeadLearner,
    OptaxLearner,
)
from ceemx.identification.solvers.base import FitState
from ceemx.infra import checkpoint as ckpt
from ceemx.infra import options
from ceemx.lib.results import RESULTS, codes, messages, select
from ceemx.systems import LinearSystem

TRACES: list[str] = []


def decay_class():
    """A new class per call, so that no compiled program is reused from an earlier test."""

    class Decay(ceemx.AbstractSystem):
        """x' = a·x + w, y = c·x + v, one parameter per kind of bound; counts traces."""

        a: Array = ceemx.param(lower=-1.0, upper=1.0)
        c: Array = ceemx.param(positive=True)
        d: Array = ceemx.param(upper=-2.0)

        @property
        def state_dim(self):
            return 1

        @property
        def obs_dim(self):
            return 1

        def dynamics(self, x, u, t):
            TRACES.append("dynamics")
            return self.a * x + 0.0 * self.d

        def observe(self, x, u, t):
            TRACES.append("observe")
            return self.c * x

    return Decay


B, T = 2, 6
DATA = ceemx.Trajectories(np.random.default_rng(0).standard_normal((B, T, 1)))
X0 = np.zeros((B, T, 1))


def decay(a=0.5, c=1.0, d=-3.0):
    return decay_class()(a=a, c=c, d=d, process_noise=0.3, obs_noise=0.3)


@pytest.fixture
def no_compute():
    """Fails the test if compute started before the refusal.

    The only trace of the system's methods allowed is the one-time check of their output shapes
    (``ceemx.models.method_check``: abstract evaluation, nothing compiled or computed); a fit,
    smoothing or health test traces them many times.
    """
    TRACES.clear()
    yield
    assert TRACES.count("dynamics") <= 1 and TRACES.count("observe") <= 1, (
        f"compute started before the refusal: {TRACES[:6]}"
    )


def raises(exc, match):
    """``exc`` whose message contains ``match``.

    Where jaxtyping + beartype check the annotations of every ceemx ``__init__`` (the slow run in
    CI, ``--jaxtyping-packages``), a value of the wrong type (``rtol="abc"``) is their
    ``TypeError`` first, naming the parameter as 'rtol'; users get ceemx's own message.
    """
    if exc is TypeError and match.startswith("`"):
        name = match[1 : match.index("`", 1)]
        rest = re.escape(match[match.index("`", 1) + 1 :])
        return pytest.raises(TypeError, match=f"`{re.escape(name)}`{rest}|parameter '{name}'")
    return pytest.raises(exc, match=re.escape(match))


# --- every option of every solver and learner validated on construction ----------------------

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
    (LMLearner, "damping", np.nan, ValueError, "finite and >= 0"),
    (LMLearner, "damping", -1.0, ValueError, "finite and >= 0"),
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
    ceemx.Alternating(learner=LMLearner(max_steps=3, damping=0.0))
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


# --- no converged=True on nonsense -------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, where, value",
    [
        (dict(c=1e-320), "system.c", "1e-320"),  # θ = −inf (subnormal flushed to zero)
        (dict(d=-2 - 4e-16), "system.d", "-2.0000000000000004"),  # LessThan(−2), one ulp off
        (dict(a=-1 + 1e-15), "system.a", "-0.999999999999999"),  # sigmoid saturated
        (dict(a=1 - 1e-15), "system.a", "0.999999999999999"),
    ],
    ids=["positive-subnormal", "upper-one-ulp", "interval-lower", "interval-upper"],
)
def test_start_on_a_bound_is_refused(no_compute, kwargs, where, value):
    system = decay(**kwargs)
    with raises(ValueError, f"`{where}` = {value}"):
        ceemx.fit(system, DATA, X0)
    with raises(ValueError, "is within rounding of its bound"):
        ceemx.fit(system, DATA, X0, solver=ceemx.JointLM())


def test_start_near_but_clear_of_a_bound_is_accepted():
    problem, theta = ceemx.FitProblem.create(decay(c=1e-300, a=-1 + 1e-12, d=-2 - 1e-12), DATA)
    assert np.all(np.isfinite(np.asarray(theta)))


def test_fixed_parameter_on_a_bound_is_not_checked():
    # Only trainable leaves must be able to move.
    problem, _ = ceemx.FitProblem.create(decay(d=-2 - 4e-16), DATA, trainable=lambda s: s.a)
    assert problem is not None


def test_absurd_start_is_refused():
    """Every start at 1e10: J ≈ −1e21 here (−2.55e67 on Lorenz), which 'converged' in 2 epochs."""
    with raises(ValueError, "the start is too far from the data to fit: trajectories 0 (r = "):
        ceemx.fit(decay(), DATA, np.full(X0.shape, 1e10))


def test_nonfinite_start_is_refused_with_outliers_kept():
    with raises(ValueError, "no trajectory has a finite objective at the start"):
        ceemx.fit(decay(), DATA, np.full(X0.shape, 1e200), outliers="keep")


# --- no quiet NaN in evaluation ----------------------------------------------------------------


def linear(a, obs_noise=0.1, b=1.0):
    one = np.ones((1, 1))
    return LinearSystem(a * one, one, b * one, 0 * one, process_noise=0.1, obs_noise=obs_noise)


RECORD = ceemx.Trajectories(
    np.random.default_rng(1).standard_normal((2, 40, 1)),
    np.random.default_rng(2).standard_normal((2, 40, 1)),
)


def test_initial_state_nan_warns_and_carries_a_status():
    """obs_noise = 1e-300: whitening overflows; x̂₁ was NaN with no warning."""
    with pytest.warns(UserWarning, match=r"x̂₁ is not finite \(NaN or inf\) for trajectories 0, 1"):
        x1, status = estimate_initial_state(linear(0.9, 1e-300), RECORD, 4, return_status=True)
    assert np.all(np.isnan(np.asarray(x1)))
    assert codes(status).tolist() == [codes(RESULTS.nonfinite)] * 2


def test_diverging_benchmark_score_warns_and_carries_a_status():
    """x_{t+1} = 1e10·x: the free run overflows; RMSE and fit % were inf/NaN with no warning."""
    start = np.array([[1.0], [0.0]])  # no input: trajectory 1 stays at 0
    with pytest.warns(UserWarning, match="free-run simulation of trajectory 0 is not finite"):
        score = benchmark_score(linear(1e10, b=0.0), RECORD, 5, x1=start)
    assert not np.isfinite(float(score.rmse_overall[0]))
    assert np.isfinite(float(score.rmse_overall[1]))
    assert messages(score.status) == [RESULTS[RESULTS.diverged], RESULTS[RESULTS.successful]]


# --- user model bugs named at the first trace ---------------------------------------------------


def buggy_class(bug):
    """A 2-state model with one bug in one method (a new class per call: nothing remembered)."""

    class Buggy(ceemx.AbstractSystem):
        a: Array = ceemx.param()

        @property
        def state_dim(self):
            return 2

        @property
        def obs_dim(self):
            return 1

        def dynamics(self, x, u, t):
            TRACES.append("dynamics")
            if bug == "dynamics-shape":
                return jnp.concatenate([x, x[:1]])
            if bug == "dynamics-scalar":
                return jnp.sum(self.a * x)
            if bug == "dynamics-dtype":
                return (self.a * x).astype(jnp.float32)
            if bug == "dynamics-tuple":
                return x, x
            if bug == "dynamics-raises":
                return x + jnp.ones(3)
            return self.a * x

        def observe(self, x, u, t):
            TRACES.append("observe")
            return x if bug == "observe-shape" else x[:1]

    return Buggy


class WrongField(ceemx.AbstractContinuousSystem):
    a: Array = ceemx.param()

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 1

    def vector_field(self, x, u, t):
        return self.a * jnp.concatenate([x, x[:1]])

    def observe(self, x, u, t):
        return x[:1]


X2 = np.zeros((B, T, 2))


@pytest.mark.parametrize(
    "bug, message",
    [
        (
            "dynamics-shape",
            "`system.dynamics` must return shape (2,) (n = 2, m = 1); it returned "
            "shape (3,) when called with x: (2,) float64, u: (0,) float64, t: ()",
        ),
        (
            "dynamics-scalar",
            "`system.dynamics` must return shape (2,) (n = 2, m = 1); it returned shape ()",
        ),
        (
            "dynamics-dtype",
            "`system.dynamics` must return the dtype of the system's parameters, "
            "float64; it returned float32",
        ),
        (
            "dynamics-tuple",
            "`system.dynamics` must return one array of shape (2,); it returned a tuple",
        ),
        ("dynamics-raises", "`system.dynamics` failed when called with x: (2,) float64"),
        (
            "observe-shape",
            "`system.observe` must return shape (1,) (n = 2, m = 1); it returned shape (2,)",
        ),
    ],
)
def test_model_method_bugs_are_named(bug, message):
    """Each used to fail inside XLA ("add got incompatible shapes (2,), (3,)", ...)."""
    Buggy = buggy_class(bug)
    for call in (
        lambda: ceemx.fit(Buggy(a=0.5), DATA, X2),
        lambda: ceemx.smooth(Buggy(a=0.5), DATA, X2),
        lambda: ceemx.ekf(Buggy(a=0.5), DATA),
    ):
        TRACES.clear()
        with raises(ValueError, message):
            call()
        assert TRACES.count("dynamics") <= 1 and TRACES.count("observe") <= 1  # traced once


def test_vector_field_bug_is_named():
    with raises(ValueError, "`system.vector_field` must return shape (2,)"):
        ceemx.fit(WrongField(a=0.5, dt=0.1), DATA, X2, solver=ceemx.JointLM())


def test_model_methods_traced_once_per_structure():
    Good = buggy_class(None)
    TRACES.clear()
    for _ in range(3):
        check_inputs(Good(a=0.5), DATA, X2)
    assert TRACES == ["dynamics", "observe"]


# --- checkpoints on full disks; what a resume trusts --------------------------------------------


def fit_state(weights=(1.0, 1.0), lam=1e-3):
    return FitState(
        theta=jnp.zeros(3),
        states=jnp.zeros((2, 4, 1)),
        J=jnp.zeros(2),
        weights=jnp.asarray(weights),
        status=select(jnp.zeros(2, bool), RESULTS.nonfinite, RESULTS.successful),
        solver_state=jnp.asarray(lam),
    )


# A fingerprint for the checkpoints written here (one without would be resumed with a warning,
# as from an older ceemx: tests/test_checkpoint_safety.py).
FINGERPRINT = {"method": "a test's fit state"}


class DiskFull:
    """A file whose writes fail as on a full disk."""

    def __init__(self, f):
        self.f = f

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self.f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()


def test_full_disk_keeps_the_last_checkpoint(tmp_path, monkeypatch):
    """Was "TreePathError: Error at leaf with path (GetAttrKey(name='states'),)"."""
    folder = str(tmp_path)
    ckpt.save(folder, fit_state(), [{"epoch": 1}], FINGERPRINT)
    real = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda *a, **k: DiskFull(real(*a, **k)))
    with raises(ckpt.CheckpointError, "No space left on device"):
        ckpt.save(folder, fit_state(), [{"epoch": 1}, {"epoch": 2}], FINGERPRINT)
    monkeypatch.undo()
    assert sorted(os.listdir(folder)) == ["latest.json", "state-1.eqx"]  # nothing stray
    tree, history = ckpt.load(folder, fit_state(), fingerprint=FINGERPRINT)
    assert history == [{"epoch": 1}]


def test_full_disk_at_the_start_leaves_no_probe(tmp_path, monkeypatch):
    def full_open(path, mode="r", *args, **kwargs):
        return DiskFull(open(path, mode, *args, **kwargs))

    monkeypatch.setattr(ckpt, "open", full_open, raising=False)
    with raises(ckpt.CheckpointError, "is not writable (No space left on device)"):
        ckpt.check_folder(str(tmp_path))
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    "state, what",
    [
        (fit_state(weights=(np.nan, 1.0)), "weights"),
        (fit_state(lam=np.nan), "solver_state"),
    ],
    ids=["nan-weights", "nan-damping"],
)
def test_resume_refuses_nonfinite_weights_and_solver_scalars(tmp_path, state, what):
    """NaN weights used to resume (J then read 0), as did a NaN damping λ."""
    ckpt.save(str(tmp_path), state, [{"epoch": 1}], FINGERPRINT)
    with raises(ckpt.CheckpointError, f"non-finite values (NaN or inf) in {what}"):
        ckpt.load(str(tmp_path), fit_state(), fingerprint=FINGERPRINT)


def test_resume_refuses_a_history_that_does_not_match_its_epoch(tmp_path):
    """An emptied history resumed as converged=True with the wrong epoch count."""
    ckpt.save(str(tmp_path), fit_state(), [{"epoch": 1}, {"epoch": 2}], FINGERPRINT)
    path = tmp_path / "latest.json"
    meta = json.loads(path.read_text())
    path.write_text(json.dumps({**meta, "history": []}))
    with raises(ckpt.CheckpointError, "epoch 2 does not match the 0 epochs of its history"):
        ckpt.load(str(tmp_path), fit_state())


# --- one writer per checkpoint folder -----------------------------------------------------------

_HOLDER = """
import sys
from ceemx.infra.folder_lock import folder_lock
with folder_lock(sys.argv[1], RuntimeError):
    print("held", flush=True)
    sys.stdin.read()
"""


def hold_in_another_process(folder):
    """A process holding ``folder``'s lock until its stdin closes (imports nothing heavy)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(folder)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline() == "held\n"
    return proc


def test_a_second_writer_is_refused_naming_the_first(tmp_path):
    """Two fits on one folder used to remove each other's temporaries and crash
    (FileNotFoundError … .tmp-… -> state-8.eqx); the second is now refused at once."""
    proc = hold_in_another_process(tmp_path)
    try:
        with raises(ckpt.CheckpointError, f"is in use by another fit (pid {proc.pid} on host"):
            with ckpt.lock(str(tmp_path)):
                pass
    finally:
        proc.communicate("")
    with ckpt.lock(str(tmp_path)):  # free once the first has finished
        assert os.listdir(tmp_path) == [".lock"]
    assert os.listdir(tmp_path) == []  # removed on release


def test_the_lock_of_a_killed_writer_is_taken_over(tmp_path):
    proc = hold_in_another_process(tmp_path)
    proc.kill()
    proc.communicate()  # waits, and closes its pipes
    assert os.listdir(tmp_path) == [".lock"]  # left behind, but no longer held
    with ckpt.lock(str(tmp_path)):
        assert f"pid {os.getpid()} on host" in (tmp_path / ".lock").read_text()


def test_fit_on_a_folder_in_use_is_refused_before_compute(no_compute, tmp_path):
    """Also within one process: the lock is per open file, and held for the fit's lifetime."""
    with ckpt.lock(str(tmp_path)):
        with raises(ckpt.CheckpointError, "is in use by another fit"):
            ceemx.fit(decay(), DATA, X0, checkpoint=str(tmp_path), solver=ceemx.Alternating())
    assert os.listdir(tmp_path) == []


# --- one dtype rule everywhere; no observation-free data ----------------------------------------

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


def test_observation_free_data_is_refused():
    """y of shape (B, T, 0) was accepted: no observation to fit."""
    with raises(ValueError, "`y` has shape (2, 5, 0): no observed components (m = 0)"):
        ceemx.Trajectories(np.zeros((2, 5, 0)))
