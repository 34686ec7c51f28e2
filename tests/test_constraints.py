"""Parameter constraints (ceemx.models.constraints) and their use by FitProblem and fit.

Oracles: the closed-form inverses (softplus⁻¹, logit), central finite differences of the
transforms in float64, the system a fit starts from (fixed fields, natural units after
create/build), and the parameters a tiny simulated problem was generated with.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array
from refusals import DATA, X0, decay, raises

import ceemx
from ceemx.identification.problem import FitProblem, trainable_mask
from ceemx.models import constraints as cons

jax.config.update("jax_enable_x64", True)

param = cons.param

CASES = [
    (cons.Unconstrained(), np.array([-3.0, 0.0, 2.5])),
    (cons.Positive(), np.array([1e-6, 0.3, 1.0, 40.0])),
    (cons.GreaterThan(-2.0), np.array([-1.999, -1.0, 5.0])),
    (cons.LessThan(1.5), np.array([-10.0, 0.0, 1.49])),
    (cons.Interval(-1.0, 3.0), np.array([-0.999, 0.0, 2.5, 2.999])),
    (cons.Fixed(), np.array([-1.0, 7.0])),
]
IDS = ["unconstrained", "positive", "greater", "less", "interval", "fixed"]


@pytest.mark.parametrize("c, x", CASES, ids=IDS)
def test_round_trip(c, x):
    x = jnp.asarray(x)
    assert np.all(c.contains(np.asarray(x)))
    np.testing.assert_allclose(c.forward(c.inverse(x)), x, rtol=1e-12, atol=1e-12)
    z = jnp.linspace(-6.0, 6.0, 13)
    np.testing.assert_allclose(c.inverse(c.forward(z)), z, rtol=1e-9, atol=1e-9)
    assert np.all(c.contains(np.asarray(c.forward(z))))  # forward lands inside


@pytest.mark.parametrize("c", [c for c, _ in CASES], ids=IDS)
def test_forward_derivative_matches_finite_differences(c):
    z = jnp.linspace(-4.0, 4.0, 9)
    grad = jax.vmap(jax.grad(lambda s: c.forward(s)))(z)
    h = 1e-6
    fd = (c.forward(z + h) - c.forward(z - h)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-7, atol=1e-9)
    assert np.all(np.asarray(grad) > 0)  # increasing: a bijection onto the allowed set


def test_contains_and_descriptions():
    assert not cons.Positive().contains(np.array(0.0))
    assert cons.Positive().description == "> 0 (positive)"
    assert cons.Interval(0.0, 1.0).description == "in (0, 1)"
    np.testing.assert_array_equal(
        cons.Interval(0, 1).contains(np.array([0.0, 0.5, 1.0])), [0, 1, 0]
    )
    assert not cons.Fixed.trainable and cons.Positive.trainable


def test_param_builds_the_declared_constraint():
    def constraint_of(field):
        return field.metadata[cons.CONSTRAINT_KEY]

    assert isinstance(constraint_of(param()), cons.Unconstrained)
    assert isinstance(constraint_of(param(positive=True)), cons.Positive)
    assert constraint_of(param(lower=1.0)) == cons.GreaterThan(1.0)
    assert constraint_of(param(upper=2.0)) == cons.LessThan(2.0)
    assert constraint_of(param(lower=0.0, upper=1.0)) == cons.Interval(0.0, 1.0)
    assert isinstance(constraint_of(param(fixed=True)), cons.Fixed)
    assert constraint_of(param(metadata={"note": 1}, default=1.0)).trainable
    with pytest.raises(ValueError, match="positive and lower/upper"):
        param(positive=True, lower=0.0)
    with pytest.raises(ValueError, match="fixed"):
        param(fixed=True, upper=1.0)
    with pytest.raises(ValueError, match="`lower` must be < `upper`"):
        param(lower=1.0, upper=1.0)
    with pytest.raises(ValueError, match="static"):
        param(static=True)
    with pytest.raises(TypeError, match="AbstractConstraint"):
        param(constraint="positive")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="finite"):
        cons.GreaterThan(float("inf"))


# A discrete-time system with constrained parameters and a nested module.
class Gain(eqx.Module):
    g: Array = param(positive=True)
    offset: Array = param()


class Leaky(ceemx.AbstractSystem):
    """x_{t+1} = a x_t + g u_t,  y_t = c x_t + offset (a ∈ (0, 1), g > 0, c fixed)."""

    a: Array = param(lower=0.0, upper=1.0)
    gain: Gain
    c: Array = param(fixed=True, default=1.0)

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.a * x + self.gain.g * u

    def observe(self, x, u, t):
        return self.c * x + self.gain.offset


def leaky(a=0.8, g=0.5, offset=0.1, **kw):
    return Leaky(a, Gain(g, offset), **kw)


def test_leaf_constraints_walk_nested_modules():
    s = leaky()
    found = cons.leaf_constraints(s)
    leaves = jax.tree_util.tree_leaves(s)
    assert len(found) == len(leaves)
    by_id = {id(leaf): c for leaf, c in zip(leaves, found, strict=True)}
    assert isinstance(by_id[id(s.a)], cons.Interval)
    assert isinstance(by_id[id(s.gain.g)], cons.Positive)
    assert isinstance(by_id[id(s.gain.offset)], cons.Unconstrained)
    assert isinstance(by_id[id(s.c)], cons.Fixed)
    assert isinstance(by_id[id(s.process_noise.scale)], cons.Unconstrained)


def test_outer_declaration_wins():
    class Outer(eqx.Module):
        inner: Gain = param(fixed=True)

    found = cons.leaf_constraints(Outer(Gain(1.0, 0.0)))
    assert all(isinstance(c, cons.Fixed) for c in found) and len(found) == 2


def test_converter_makes_float_arrays():
    s = leaky(a=0.5, g=2, offset=np.int32(1))
    assert isinstance(s.gain.g, jax.Array) and jnp.issubdtype(s.gain.g.dtype, jnp.floating)
    assert s.a.weak_type  # Python scalars stay weakly typed
    assert jnp.issubdtype(jnp.asarray(s.gain.offset).dtype, jnp.floating)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(a=1.2), r"`system.a` must be in \(0, 1\); got 1.2"),
        (dict(g=-0.3), r"`system.gain.g` must be > 0 \(positive\); got -0.3"),
        (dict(g=jnp.array([0.1, 0.0])), r"`system.gain.g` must be > 0 \(positive\); entry \(1,\)"),
    ],
    ids=["interval", "nested-positive", "vector"],
)
def test_bad_values_raise_naming_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        leaky(**kw)


def test_create_checks_constraints_of_a_modified_system():
    s = eqx.tree_at(lambda s: s.gain.g, leaky(), jnp.asarray(-0.3))  # tree_at skips __init__
    data = ceemx.Trajectories(np.zeros((1, 4, 1)), np.zeros((1, 4, 1)))
    with pytest.raises(ValueError, match=r"`system.gain.g` must be > 0 \(positive\); got -0.3"):
        FitProblem.create(s, data)


def test_trainable_mask_drops_fixed_fields():
    s = leaky()
    for trainable in (None, lambda s: (s.a, s.c), jax.tree_util.tree_map(lambda _: True, s)):
        mask = trainable_mask(s, trainable)
        assert mask.c is False
        assert mask.a is True
    assert trainable_mask(s).process_noise.scale is False
    # A prefix filter spec is broadcast over the sub-tree.
    prefix = jax.tree_util.tree_map(lambda _: False, s)
    prefix = eqx.tree_at(lambda t: t.gain, prefix, True)
    mask = trainable_mask(s, prefix)
    assert mask.gain.g is True and mask.gain.offset is True and mask.a is False


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_theta_is_unconstrained_and_build_is_natural(dtype):
    s = leaky(a=jnp.asarray(0.8, dtype), g=jnp.asarray(0.5, dtype), offset=jnp.asarray(0.1, dtype))
    data = ceemx.Trajectories(np.zeros((1, 4, 1), dtype), np.zeros((1, 4, 1), dtype))
    problem, theta = FitProblem.create(s, data)
    assert theta.dtype == dtype and not theta.weak_type
    expected = [np.log(0.8 / 0.2), np.log(np.expm1(0.5)), 0.1]  # a, g, offset (c is fixed)
    np.testing.assert_allclose(theta, expected, rtol=1e-6)
    built = problem.build(theta)
    for get in (lambda t: t.a, lambda t: t.gain.g, lambda t: t.gain.offset):
        np.testing.assert_allclose(get(built), get(s), rtol=1e-6)
        assert get(built).dtype == dtype
    # fixed: part of the static rest, its value kept; strongly typed in the system's dtype (a weak
    # leaf would make the problem's programs differ from those of the promoted system)
    np.testing.assert_array_equal(built.c, s.c)
    assert built.c.dtype == dtype and not built.c.weak_type
    # Any θ builds a system inside the constraints.
    far = problem.build(jnp.asarray([40.0, -30.0, 0.0], dtype))
    assert 0.0 < float(far.a) <= 1.0 and float(far.gain.g) > 0.0


def test_build_is_differentiable_and_jit_friendly():
    s = leaky()
    data = ceemx.Trajectories(np.zeros((1, 4, 1)), np.zeros((1, 4, 1)))
    problem, theta = FitProblem.create(s, data)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def natural_g(problem, theta):
        return problem.build(theta).gain.g

    assert float(natural_g(problem, theta)) == pytest.approx(0.5)
    natural_g(problem, theta + 0.1)  # new values: no retrace
    d = jax.grad(lambda th: problem.build(th).gain.g)(theta)
    np.testing.assert_allclose(d, [0.0, jax.nn.sigmoid(theta[1]), 0.0], rtol=1e-12)


def simulated(T=60, B=3, seed=0):
    true = leaky(a=0.8, g=0.5, offset=0.1, process_noise=0.02, obs_noise=0.02)
    u = jax.random.normal(jax.random.PRNGKey(seed), (B, T, 1))
    _, data = ceemx.simulate(true, jax.random.PRNGKey(seed + 1), jnp.zeros((B, 1)), T, u)
    return true, data


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["alternating", pytest.param("joint", marks=pytest.mark.slow)])
def test_fit_keeps_parameters_inside_and_reports_natural_units(solver):
    true, data = simulated()
    # Start far off: g close to its bound and a at the edge of (0, 1); c fixed at a wrong value
    # stays there (it is never learned).
    guess = leaky(a=0.05, g=0.01, offset=0.0, process_noise=0.02, obs_noise=0.02, c=1.05)
    fit_solver = ceemx.Alternating() if solver == "alternating" else ceemx.JointLM()
    seen = []
    result = ceemx.fit(
        guess,
        data,
        solver=fit_solver,
        max_epochs=40,
        callbacks=[lambda info: seen.append((float(info.system.a), float(info.system.gain.g)))],
    )
    s = result.system
    assert all(0.0 < a < 1.0 and g > 0.0 for a, g in seen)  # every epoch inside
    assert float(s.c) == 1.05  # fixed: unchanged, exactly
    np.testing.assert_allclose(float(s.a), 0.8, atol=0.08)  # natural units
    np.testing.assert_allclose(float(s.gain.g), 0.5 / 1.05, rtol=0.15)


@pytest.mark.slow  # ≈ 2.5 s; resume is checked in test_checkpoint_safety
def test_fit_with_lm_learner_and_checkpoint_resume(tmp_path):
    true, data = simulated(T=40, B=2)
    guess = leaky(a=0.3, g=2.0, offset=0.0, process_noise=0.02, obs_noise=0.02)
    # Four epochs are not a fit whose residuals say anything about the noise: no noise check.
    solver, kw = ceemx.Alternating(learner=ceemx.LMLearner()), dict(diagnose=False)
    full = ceemx.fit(guess, data, solver=solver, max_epochs=4, **kw)
    folder = str(tmp_path / "ckpt")
    ceemx.fit(guess, data, solver=solver, max_epochs=2, checkpoint=folder, **kw)
    resumed = ceemx.fit(guess, data, solver=solver, max_epochs=4, checkpoint=folder, **kw)
    for get in (lambda t: t.a, lambda t: t.gain.g, lambda t: t.gain.offset):
        np.testing.assert_allclose(get(resumed.system), get(full.system), rtol=1e-10)
    assert float(full.system.gain.g) > 0 and 0 < float(full.system.a) < 1


def test_fields_carry_metadata():
    names = {f.name: f.metadata.get(cons.CONSTRAINT_KEY) for f in dataclasses.fields(Leaky)}
    assert isinstance(names["a"], cons.Interval) and names["process_noise"] is None


@pytest.mark.slow  # ≈ 2.3 s of ParticleEM compilation
def test_particle_em_learns_unconstrained():
    true, data = simulated(T=30, B=2)
    prior = ceemx.GaussianPrior(jnp.zeros(1), ceemx.DiagonalGaussian(0.5, 1))
    guess = leaky(
        a=0.3, g=0.02, offset=0.0, process_noise=0.02, obs_noise=0.02, c=1.05, initial_prior=prior
    )
    result = ceemx.fit(
        guess,
        data,
        solver=ceemx.ParticleEM(n_particles=32, n_smoothed=4, burn_in=1, memory=2),
        max_epochs=4,
        key=jax.random.PRNGKey(3),
        diagnose=False,  # four epochs are not a fit whose residuals say anything about the noise
    )
    s = result.system
    assert 0.0 < float(s.a) < 1.0 and float(s.gain.g) > 0.0
    assert float(s.c) == 1.05
    assert float(s.a) > 0.3 and float(s.gain.g) > 0.02  # it moved towards (0.8, 0.5)


# --- a fit refuses a start on a bound (θ = ±∞ in unconstrained units) before any compute ----------


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
    # just clear of the scale check's limits (1e-100 from 0; 1e-10 of the interval's width or |b|)
    problem, theta = ceemx.FitProblem.create(decay(c=1e-90, a=-1 + 1e-9, d=-2 - 1e-9), DATA)
    assert np.all(np.isfinite(np.asarray(theta)))


def test_fixed_parameter_on_a_bound_is_not_checked():
    # Only trainable leaves must be able to move.
    problem, _ = ceemx.FitProblem.create(decay(d=-2 - 4e-16), DATA, trainable=lambda s: s.a)
    assert problem is not None
