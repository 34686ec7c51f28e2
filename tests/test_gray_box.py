"""The gray-box models of the real datasets: construction, shapes, constraints, smoothness, fits."""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.systems import CascadedTanks, CoupledDrives, Silverbox
from ceemx.systems.gray_box import smooth_abs, smooth_sqrt, soft_min

jax.config.update("jax_enable_x64", True)

T = 160

# (class, typical initial state, input amplitude, parameters that must be positive)
CASES = [
    (CascadedTanks, [3.0, 4.0], 5.0, ("k1", "k2", "k3", "k4", "h")),
    (Silverbox, [0.0, 0.0], 0.1, ("f0", "zeta")),
    (CoupledDrives, [0.0, 0.0, 0.0], 1.0, ("a", "f0", "zeta")),
]
IDS = [c[0].__name__ for c in CASES]


def _inputs(cls, amplitude, batch=2, length=T):
    key = jax.random.PRNGKey(0)
    if cls is CascadedTanks:  # a slow positive pump voltage
        steps = jax.random.uniform(key, (batch, length // 20, 1), minval=0.3, maxval=1.4)
        return amplitude * jnp.repeat(steps, 20, axis=1)
    return amplitude * jax.random.normal(key, (batch, length, 1))


@pytest.mark.parametrize(("cls", "x1", "amp", "positive"), CASES, ids=IDS)
def test_construction_shapes_and_finite(cls, x1, amp, positive):
    system = cls.default()
    assert system.input_dim == system.control_dim == 1
    assert system.obs_dim == 1 and system.state_dim == len(x1)
    u = _inputs(cls, amp)
    x0 = jnp.asarray([x1, x1], dtype=jnp.float64)
    xs, data = ceemx.simulate(system, jax.random.PRNGKey(1), x0, T, u)
    assert xs.shape == (2, T, system.state_dim)
    assert data.y.shape == (2, T, 1)
    assert bool(jnp.all(jnp.isfinite(xs))) and bool(jnp.all(jnp.isfinite(data.y)))
    assert data.y.dtype == jnp.float64
    for name in positive:
        assert float(getattr(system, name)) > 0


@pytest.mark.parametrize(("cls", "x1", "amp", "positive"), CASES, ids=IDS)
def test_constraints_are_declared_and_checked(cls, x1, amp, positive):
    system = cls.default()
    with pytest.raises(ValueError, match="positive"):
        cls.default(**{positive[0]: -0.5})
    assert all(float(getattr(system, name)) > 0 for name in positive)


@pytest.mark.parametrize(("cls", "x1", "amp", "positive"), CASES, ids=IDS)
def test_derivatives_finite_at_zero(cls, x1, amp, positive):
    system = cls.default()
    x = jnp.zeros(system.state_dim)
    u = jnp.array([amp])

    def total(x, s):
        return jnp.sum(s.dynamics(x, u, 0)) + jnp.sum(s.observe(x, u, 0))

    # One compiled program for the three derivatives (reverse mode in x and θ in one pass, forward
    # mode in x): op by op they cost about twice the compilation (4–9 s for the tanks' RK4 steps).
    @jax.jit
    def derivatives(x, s):
        return jax.grad(total, argnums=(0, 1))(x, s), jax.jacfwd(lambda x: s.dynamics(x, u, 0))(x)

    (gx, gtheta), jac = derivatives(x, system)
    assert bool(jnp.all(jnp.isfinite(gx)))
    leaves = jax.tree_util.tree_leaves(gtheta)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    assert bool(jnp.all(jnp.isfinite(jac)))


def test_smooth_primitives():
    x = jnp.array([0.0, 1e-2, 1.0, 9.0, -4.0])
    np.testing.assert_allclose(smooth_sqrt(x)[2:4], [1.0, 3.0], rtol=1e-4)
    assert float(smooth_sqrt(x)[4]) < 0  # odd: a negative level gives a restoring flow
    assert np.isfinite(float(jax.grad(smooth_sqrt)(0.0)))
    np.testing.assert_allclose(smooth_abs(jnp.array([-3.0, 3.0])), [3.0, 3.0], rtol=1e-5)
    assert float(jax.grad(smooth_abs)(0.0)) == 0.0
    sat = soft_min(jnp.array([2.0, 10.0, 14.0]), 10.0, 10.0)
    np.testing.assert_allclose(sat[0], 2.0, atol=1e-12)
    assert float(sat[2]) <= 10.0 and float(sat[1]) < 10.0


def test_tanks_overflow_and_saturation():
    tanks = CascadedTanks.default()
    u = jnp.array([10.0])
    # far above the overflow level the upper tank receives no inflow, the lower tank φ of it
    f = tanks.vector_field(jnp.array([12.0, 4.0]), u, 0.0)
    assert float(f[0]) < 0
    below = tanks.vector_field(jnp.array([4.0, 4.0]), u, 0.0)
    assert float(below[0]) > 0
    y = tanks.observe(jnp.array([1.0, 20.0]), u, 0.0)
    assert float(y[0]) <= 10.0 + 1e-12


def test_tanks_lower_level_stays_below_its_rim():
    """A free run pumping hard: the lower tank overflows at its rim instead of filling on."""
    tanks = CascadedTanks.default()
    u = jnp.full((150, 1), 8.0)  # steady state far above both rims
    x, y = ceemx.free_run(tanks, jnp.array([3.0, 4.0]), u)
    rim = float(jnp.asarray(tanks.h2) - jnp.asarray(tanks.offset))
    assert float(x[:, 1].max()) > rim - 0.5  # it does reach the rim…
    assert float(x[:, 1].max()) < rim + 0.3  # …and stays there (smooth gate, β₂ = 10/V)
    assert float(y.max()) <= 10.0
    no_rim = CascadedTanks.default(h2=1e3)  # the model without the lower overflow fills on
    x_free, _ = ceemx.free_run(no_rim, jnp.array([3.0, 4.0]), u)
    assert float(x_free[:, 1].max()) > rim + 2.0
    # below the rim the gate is closed: the model is the one without the lower overflow
    low = jnp.array([2.0, 3.0])
    np.testing.assert_allclose(
        tanks.vector_field(low, u[0], 0.0), no_rim.vector_field(low, u[0], 0.0), rtol=1e-10
    )


def _fit_check(true, guess, trainable, u, x1, names, rtol, max_epochs=15):
    x0 = jnp.broadcast_to(jnp.asarray(x1, dtype=jnp.float64), (u.shape[0], true.state_dim))
    _, data = ceemx.simulate(true, jax.random.PRNGKey(3), x0, u.shape[1], u)
    result = ceemx.fit(
        guess, data, solver=ceemx.JointLM(), trainable=trainable, max_epochs=max_epochs
    )
    for name in names:
        got, want = float(getattr(result.system, name)), float(getattr(true, name))
        start = float(getattr(guess, name))
        assert abs(got - want) <= rtol * abs(want), (name, start, got, want)


# One identification per system compiles its own JointLM (4–7 s each): all three run under `slow`
# (the models are checked above; the JointLM fit itself has its own default-tier tests).
@pytest.mark.slow
def test_identify_tanks_outflows():
    options: dict[str, Any] = dict(process_noise=1e-3, obs_noise=1e-2)
    true = CascadedTanks.default(**options)
    guess = CascadedTanks.default(k1=0.035, k4=0.032, **options)
    u = _inputs(CascadedTanks, 5.0)
    _fit_check(true, guess, lambda s: (s.k1, s.k4), u, [3.0, 4.0], ("k1", "k4"), 0.1)


@pytest.mark.slow  # a JointLM fit (≈ 5 s of compilation; tanks and drives too)
def test_identify_silverbox_frequency_and_cubic():
    options: dict[str, Any] = dict(process_noise=1e-4, obs_noise=1e-3)
    true = Silverbox.default(kappa=20.0, **options)
    guess = Silverbox.default(f0=55.0, kappa=5.0, **options)
    u = _inputs(Silverbox, 0.15)
    _fit_check(true, guess, lambda s: (s.f0, s.kappa), u, [0.0, 0.0], ("f0", "kappa"), 0.1)


@pytest.mark.slow
def test_identify_drives_rate_and_gain():
    options: dict[str, Any] = dict(process_noise=1e-3, obs_noise=1e-2)
    true = CoupledDrives.default(**options)
    guess = CoupledDrives.default(a=1.3, gain=1.3, **options)
    u = _inputs(CoupledDrives, 1.0)
    _fit_check(true, guess, lambda s: (s.a, s.gain), u, [0.0, 0.0, 0.0], ("a", "gain"), 0.1)


def test_drives_offsets_and_sensor_power():
    """y = y₀ + (v² + ε)^{p/2} (p = 1: the smooth |v|); the motor is at rest when u = u₀."""
    s = CoupledDrives.default(u0=0.3, y0=-0.1, power=2.0)
    x = jnp.array([0.5, -1.5, 0.2])
    np.testing.assert_allclose(s.observe(x, jnp.array([0.0]), 0), [-0.1 + 1.5**2 + 1e-3])
    flat = CoupledDrives.default()
    want = smooth_abs(jnp.array([-1.5]), 1e-3)
    np.testing.assert_allclose(flat.observe(x, jnp.array([0.0]), 0), want)
    f = s.vector_field(jnp.array([0.7, 0.0, 0.0]), jnp.array([0.3]), 0)
    np.testing.assert_allclose(f[0], -float(s.a) * 0.7)
