"""Custom (gray-box) systems: keyword construction with defaulted base fields, checks on
construction, first-order hold and RK4 substeps, and the example of docs/custom_systems.md.

Oracles: the exact discretisation of a linear system (matrix exponential of the augmented system,
for zero- and first-order hold), RK4's fourth order, the legacy ``rk4_step``, and the parameters
the documented example was simulated with.
"""

import pathlib
import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from jaxtyping import Array
from refusals import DATA, TRACES, B, T, raises

import ceemx
from ceemx.data.checks import check_inputs
from ceemx.data.trajectories import foh_inputs
from ceemx.models import constraints as cons
from ceemx.models.system import rk4_step
from ceemx.systems import CoupledLorenz, LinearSystem

jax.config.update("jax_enable_x64", True)


class MassSpringDamper(ceemx.AbstractContinuousSystem):
    k: Array = cons.param(positive=True)
    c: Array = cons.param(positive=True)

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
        return jnp.stack([x[1], u[0] - self.k * x[0] - self.c * x[1]])

    def observe(self, x, u, t):
        return x[:1]


def test_keyword_and_positional_construction():
    a = MassSpringDamper(k=2.0, c=0.5, dt=0.1)
    b = MassSpringDamper(2.0, 0.5, dt=0.1)
    assert eqx.tree_equal(a, b)
    assert isinstance(a.process_noise, ceemx.DiagonalGaussian) and a.process_noise.dim == 2
    assert isinstance(a.obs_noise, ceemx.DiagonalGaussian) and a.obs_noise.dim == 1
    assert float(a.process_noise.scale) == 1.0 and a.initial_prior is None
    assert (a.hold, a.substeps, a.dt) == ("zoh", 1, 0.1)
    s = MassSpringDamper(2.0, 0.5, dt=0.1, process_noise=0.1, obs_noise=np.array([0.2]))
    np.testing.assert_allclose(s.process_noise.std(), [0.1, 0.1])
    np.testing.assert_allclose(s.obs_noise.std(), [0.2])
    with pytest.raises(TypeError):
        MassSpringDamper(2.0, 0.5, 0.1)  # pyright: ignore[reportCallIssue] - base fields keyword-only
    with pytest.raises(TypeError, match="dt"):
        MassSpringDamper(2.0, 0.5)  # pyright: ignore[reportCallIssue]


def test_noise_scales_take_the_parameters_dtype():
    s = MassSpringDamper(
        jnp.asarray(2.0, jnp.float32), jnp.asarray(0.5, jnp.float32), dt=0.1, process_noise=0.1
    )
    assert s.process_noise.scale.dtype == jnp.float32
    assert s.obs_noise.scale.dtype == jnp.float32
    noise = ceemx.StudentT(0.1, 4.0, 1)
    assert MassSpringDamper(2.0, 0.5, dt=0.1, obs_noise=noise).obs_noise is noise
    prior = ceemx.GaussianPrior(jnp.zeros(2), ceemx.DiagonalGaussian(1.0, 2))
    assert MassSpringDamper(2.0, 0.5, dt=0.1, initial_prior=prior).initial_prior is prior
    moved = ceemx.with_noise(MassSpringDamper(2.0, 0.5, dt=0.1), 0.3, 0.4)
    np.testing.assert_allclose(moved.obs_noise.std(), [0.4])


def test_user_post_init_runs_after_the_defaults():
    seen = []

    class Decay(ceemx.AbstractSystem):
        a: Array

        def __post_init__(self):
            seen.append(type(self.process_noise).__name__)

        state_dim = property(lambda self: 1)
        obs_dim = property(lambda self: 1)

        def dynamics(self, x, u, t):
            return self.a * x

        def observe(self, x, u, t):
            return x

    Decay(jnp.asarray(0.5), obs_noise=0.1)
    assert seen == ["DiagonalGaussian"]


def test_hand_written_init_and_redeclared_fields():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no Equinox warning about an unrun __post_init__

        class Hand(ceemx.AbstractSystem):
            a: Array

            def __init__(self, a, noise):
                self.a = jnp.asarray(a)
                self.process_noise = noise
                self.obs_noise = ceemx.DiagonalGaussian(1.0, 1)
                self.initial_prior = None

            state_dim = property(lambda self: 1)
            obs_dim = property(lambda self: 1)

            def dynamics(self, x, u, t):
                return self.a * x

            def observe(self, x, u, t):
                return x

        class Redeclared(ceemx.AbstractSystem):  # the pre-defaults style (tests/test_filtering.py)
            a: Array
            process_noise: ceemx.AbstractNoise
            obs_noise: ceemx.AbstractNoise
            initial_prior: ceemx.GaussianPrior | None

            state_dim = property(lambda self: 1)
            obs_dim = property(lambda self: 1)

            def dynamics(self, x, u, t):
                return self.a * x

            def observe(self, x, u, t):
                return x

    assert Hand(0.5, ceemx.DiagonalGaussian(0.1, 1)).process_noise.dim == 1
    with pytest.raises(TypeError, match="`system.process_noise` must be a noise model; got float"):
        Hand(0.5, 0.1)
    unit = ceemx.DiagonalGaussian(1.0, 1)
    r = Redeclared(a=jnp.asarray(0.5), process_noise=unit, obs_noise=unit, initial_prior=None)
    assert r.obs_noise is unit
    # The built-in systems (hand-written __init__) construct as before.
    lin = LinearSystem(jnp.eye(2), jnp.ones((1, 2)), process_noise=0.1)
    assert lin.process_noise.dim == 2 and lin.input_dim == 0
    lz = CoupledLorenz(jnp.array([10.0]), jnp.array([28.0]), jnp.array([8 / 3]), jnp.eye(3))
    assert (lz.hold, lz.substeps, lz.dt, lz.input_dim) == ("zoh", 1, 0.04, 0)


@pytest.mark.parametrize(
    "kw, error, match",
    [
        (
            dict(process_noise=ceemx.DiagonalGaussian(1.0, 3)),
            ValueError,
            "`system.process_noise` has dimension 3 but the system's state_dim is 2",
        ),
        (
            dict(obs_noise=jnp.ones(3)),
            ValueError,
            r"`system.obs_noise.scale` must be a scalar or have shape \(1,\)",
        ),
        (
            dict(process_noise=ceemx.CholeskyGaussian(jnp.eye(3))),
            ValueError,
            "`system.process_noise` has dimension 3",
        ),
        (
            dict(initial_prior=ceemx.GaussianPrior(jnp.zeros(3), ceemx.DiagonalGaussian(1.0, 2))),
            ValueError,
            r"`system.initial_prior.mean` must have shape \(state_dim,\) = \(2,\)",
        ),
        (
            dict(initial_prior=ceemx.GaussianPrior(jnp.zeros(2), ceemx.DiagonalGaussian(1.0, 3))),
            ValueError,
            "`system.initial_prior.noise` has dimension 3",
        ),
        (dict(initial_prior=0.1), TypeError, "`system.initial_prior` must be a ceemx.Gaussian"),
        (dict(c=jnp.asarray(0.5, jnp.float32)), ValueError, "`system.c` has dtype float32"),
        (dict(k=jnp.asarray(jnp.nan)), ValueError, "`system.k` must be finite"),
        (dict(k=-1.0), ValueError, r"`system.k` must be > 0 \(positive\); got -1.0"),
        (dict(dt=0.0), ValueError, "`system.dt` must be a positive finite number"),
        (dict(hold="cubic"), ValueError, "`system.hold` must be 'zoh' or 'foh'"),
        (dict(substeps=0), ValueError, "`system.substeps` must be an integer >= 1"),
    ],
    ids=[
        "process-dim", "obs-scale-shape", "cholesky-dim", "prior-mean", "prior-noise",
        "prior-type", "dtype", "nan", "constraint", "dt", "hold", "substeps",
    ],
)  # fmt: skip
def test_check_init_errors_name_the_field(kw, error, match):
    args = dict(k=jnp.asarray(2.0, jnp.float64), c=jnp.asarray(0.5, jnp.float64), dt=0.1) | kw
    with pytest.raises(error, match=match):
        MassSpringDamper(**args)


def test_foh_needs_control_dim():
    class OnlyInputDim(ceemx.AbstractContinuousSystem):  # the zero-order-hold-only style
        a: Array

        state_dim = property(lambda self: 1)
        obs_dim = property(lambda self: 1)
        input_dim = property(lambda self: 1)

        def vector_field(self, x, u, t):
            return -self.a * x + u

        def observe(self, x, u, t):
            return x

    assert OnlyInputDim(jnp.asarray(1.0), dt=0.1).input_dim == 1  # zoh: still fine
    with pytest.raises(ValueError, match="declare the number of inputs p with `control_dim`"):
        OnlyInputDim(jnp.asarray(1.0), dt=0.1, hold="foh")


def test_foh_inputs():
    u = jnp.arange(12.0).reshape(2, 3, 2)
    stacked = foh_inputs(u)
    assert stacked.shape == (2, 3, 4)
    np.testing.assert_array_equal(stacked[..., :2], u)
    np.testing.assert_array_equal(stacked[:, :-1, 2:], u[:, 1:])
    np.testing.assert_array_equal(stacked[:, -1, 2:], u[:, -1])  # the last step repeats u_T
    mask = np.ones((2, 3, 1), bool)
    mask[0, 1] = False
    data = ceemx.Trajectories(np.ones((2, 3, 1)), u, mask)
    out = foh_inputs(data)
    np.testing.assert_array_equal(out.u, stacked)
    np.testing.assert_array_equal(out.mask, data.mask)
    np.testing.assert_array_equal(out.y, data.y)
    np.testing.assert_array_equal(foh_inputs(u[0]), stacked[0])  # one record (T, p)
    with pytest.raises(ValueError, match="inputs must have shape"):
        foh_inputs(jnp.ones(3))


# A linear continuous-time system ẋ = A x + B u, for the exact discretisations.
A = np.array([[0.0, 1.0], [-4.0, -0.6]])
BU = np.array([[0.5, 0.0], [1.0, -0.3]])
DT = 0.2


class LinearCT(ceemx.AbstractContinuousSystem):
    A: Array
    B: Array

    @property
    def state_dim(self):
        return self.A.shape[0]

    @property
    def obs_dim(self):
        return self.A.shape[0]

    @property
    def control_dim(self):
        return self.B.shape[1]

    def vector_field(self, x, u, t):
        return self.A @ x + self.B @ u

    def observe(self, x, u, t):
        return x


def exact_step(hold, x, u0, u1):
    """x(dt) by the matrix exponential of the system augmented with the input (and its slope)."""
    n, p = BU.shape
    if hold == "zoh":
        M = np.zeros((n + p, n + p))
        M[:n, :n], M[:n, n:] = A, BU
        E = scipy.linalg.expm(M * DT)
        return E[:n, :n] @ x + E[:n, n:] @ u0
    # z = (x, v, w): ẋ = A x + B v, v̇ = w / dt, ẇ = 0, with v(0) = u_t, w = u_{t+1} − u_t.
    M = np.zeros((n + 2 * p, n + 2 * p))
    M[:n, :n], M[:n, n : n + p] = A, BU
    M[n : n + p, n + p :] = np.eye(p) / DT
    E = scipy.linalg.expm(M * DT)
    return E[:n, :n] @ x + E[:n, n : n + p] @ u0 + E[:n, n + p :] @ (u1 - u0)


def one_step(hold, substeps, x, u0, u1, t=3):
    s = LinearCT(jnp.asarray(A), jnp.asarray(BU), dt=DT, hold=hold, substeps=substeps)
    u = jnp.concatenate([u0, u1]) if hold == "foh" else jnp.asarray(u0)
    return np.asarray(eqx.filter_jit(lambda s, x, u: s.dynamics(x, u, t))(s, jnp.asarray(x), u))


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_holds_match_the_exact_discretisation(hold):
    x = np.array([1.0, -0.5])
    u0, u1 = np.array([0.7, -1.2]), np.array([-0.4, 0.9])
    exact = exact_step(hold, x, u0, u1)
    np.testing.assert_allclose(one_step(hold, 64, x, u0, u1), exact, rtol=0, atol=5e-11)
    # RK4's fourth order: halving the substep divides the error by about 16.
    e2 = np.abs(one_step(hold, 2, x, u0, u1) - exact).max()
    e4 = np.abs(one_step(hold, 4, x, u0, u1) - exact).max()
    assert 12 < e2 / e4 < 20
    other = exact_step("foh" if hold == "zoh" else "zoh", x, u0, u1)
    assert np.abs(other - exact).max() > 1e-2  # the holds really differ


def test_foh_with_constant_input_is_zoh_and_legacy_step_is_unchanged():
    x, u0 = np.array([1.0, -0.5]), np.array([0.7, -1.2])
    np.testing.assert_allclose(
        one_step("foh", 3, x, u0, u0), one_step("zoh", 3, x, u0, None), rtol=1e-14
    )
    s = LinearCT(jnp.asarray(A), jnp.asarray(BU), dt=DT)
    legacy = rk4_step(s.vector_field, jnp.asarray(x), jnp.asarray(u0), 3 * DT, DT)
    np.testing.assert_array_equal(s.dynamics(jnp.asarray(x), jnp.asarray(u0), 3), legacy)


def test_foh_observe_sees_the_stacked_pair():
    s = LinearCT(jnp.asarray(A), jnp.asarray(BU), dt=DT, hold="foh")
    assert (s.control_dim, s.input_dim) == (2, 4)
    np.testing.assert_array_equal(s.current_input(jnp.arange(4.0)), [0.0, 1.0])


@pytest.mark.slow  # the documented example's fits (≈ 5 s)
def test_documented_example_runs():
    assert ceemx.param is cons.param
    text = (pathlib.Path(__file__).parents[1] / "docs" / "custom_systems.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    code = next(b for b in blocks if "class MassSpringDamper" in b)
    namespace: dict = {}
    exec(compile(code, "custom_systems.md", "exec"), namespace)
    result, true = namespace["result"], namespace["true"]
    assert result.converged
    assert float(result.system.k) > 0 and float(result.system.c) > 0
    np.testing.assert_allclose(float(result.system.k), float(true.k), rtol=0.02)
    np.testing.assert_allclose(float(result.system.c), float(true.c), rtol=0.05)
    assert float(result.system.m) == 1.0  # fixed
    bounded = namespace["bounded"]  # per-fit bounds and fixed values
    assert 0 < float(bounded.system.k) < 10 and float(bounded.system.m) == 1.0
    np.testing.assert_allclose(float(bounded.system.k), float(true.k), rtol=0.02)


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
