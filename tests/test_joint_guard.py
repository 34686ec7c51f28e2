"""The guarded joint method (its trust region and smoothing check) and the default start.

A mechanical system with Coulomb + viscous friction, position measured, velocity hidden, a long
record: from ``x_init=None`` both methods reach the same optimum; from a start with the velocity
at zero the joint method's trust region keeps it from the poor stationary point it reached
without one; the smoothing check refuses to stop where a smoothing pass still gains.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.initialize import from_observations
from ceemx.models import DiagonalGaussian

jax.config.update("jax_enable_x64", True)


class Friction(ceemx.AbstractContinuousSystem):
    """m ẍ = u − k x − c ẋ − F_c tanh(ẋ/ε) with m = 1, log-parametrised k, c, F_c."""

    log_k: jax.Array
    log_c: jax.Array
    log_fc: jax.Array
    process_noise: ceemx.AbstractNoise
    obs_noise: ceemx.AbstractNoise
    initial_prior: ceemx.GaussianPrior | None
    dt: float = eqx.field(static=True)

    @property
    def state_dim(self):
        return 2

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def vector_field(self, x, u, t):
        pos, vel = x
        friction = jnp.exp(self.log_c) * vel + jnp.exp(self.log_fc) * jnp.tanh(vel / 0.01)
        return jnp.stack([vel, u[0] - jnp.exp(self.log_k) * pos - friction])

    def observe(self, x, u, t):
        return x[:1]


def make(k, c, fc):
    return Friction(
        log_k=jnp.log(jnp.asarray(k)),
        log_c=jnp.log(jnp.asarray(c)),
        log_fc=jnp.log(jnp.asarray(fc)),
        process_noise=DiagonalGaussian(jnp.array([1e-4, 1e-3]), 2),
        obs_noise=DiagonalGaussian(jnp.array([1e-3]), 1),
        initial_prior=None,
        dt=0.01,
    )


@pytest.fixture(scope="module")
def problem():
    T = 2000
    rng = np.random.default_rng(0)
    u = np.repeat(rng.normal(0.0, 2.0, (T // 50, 1)), 50, axis=0)[None]
    _, data = ceemx.simulate(
        make(4.0, 0.5, 0.3), jax.random.PRNGKey(0), jnp.zeros((1, 2)), T, u=jnp.asarray(u)
    )
    return make(2.0, 1.0, 0.1), data


def natural(system):
    return np.exp([float(system.log_k), float(system.log_c), float(system.log_fc)])


@pytest.mark.slow  # Alternating's programs (≈ 5 s); the guard's own oracles stay below
def test_both_methods_and_starts_reach_the_same_optimum(problem):
    """Joint from the default start and from zero velocity, and Algorithm 1: one optimum."""
    guess, data = problem
    alt = ceemx.fit(guess, data, solver=ceemx.Alternating(), max_epochs=100)
    joint = ceemx.fit(guess, data, solver=ceemx.JointLM(), max_epochs=100)
    zero_velocity = ceemx.fit(
        guess, data, from_observations(guess, data), solver=ceemx.JointLM(), max_epochs=100
    )
    assert alt.converged and joint.converged and zero_velocity.converged
    np.testing.assert_allclose(natural(joint.system), natural(alt.system), rtol=1e-5)
    np.testing.assert_allclose(natural(zero_velocity.system), natural(alt.system), rtol=1e-5)
    np.testing.assert_allclose(natural(alt.system), [4.0, 0.5, 0.3], rtol=0.05)
    assert joint.history[-1]["J"] == pytest.approx(alt.history[-1]["J"], rel=1e-9)


@pytest.mark.slow
def test_trust_region_bounds_every_theta_step(problem):
    """From the least-squares start (velocity 0) the bounded joint steps stay in the trust region
    (that the joint method converges from there to Algorithm 1's optimum is the slow test above)."""
    guess, data = problem
    x0 = from_observations(guess, data)
    # Three epochs are not a fit whose residuals say anything about the noise: no noise check.
    solver = ceemx.JointLM(max_theta_step=0.1)
    bounded = ceemx.fit(guess, data, x0, solver=solver, max_epochs=3, diagnose=False)
    thetas = [np.array([float(guess.log_k), float(guess.log_c), float(guess.log_fc)])]
    for h in bounded.history:
        # every component of the θ step within 0.1·max(|θ_i|, 1) ⇒ the norm within 0.1·√3·max
        bound = 0.1 * np.sqrt(3) * max(1.0, np.max(np.abs(thetas[-1])))
        assert h["dtheta_norm"] <= bound * (1 + 1e-9)
    assert bounded.history[-1]["J"] > bounded.initial_J  # the bounded steps still climb
    with pytest.raises(ValueError, match="max_theta_step"):
        ceemx.JointLM(max_theta_step=0.0)


@pytest.mark.slow
def test_smoothing_check_refuses_to_stop(problem):
    """A loose rtol would stop after one step; a smoothing pass still gains, so it goes on."""
    guess, data = problem
    x0 = from_observations(guess, data)
    loose = ceemx.JointLM(rtol=0.9)
    # One epoch is not a fit whose residuals say anything about the noise: no noise check.
    checked = ceemx.fit(guess, data, x0, solver=loose, max_epochs=1, diagnose=False)
    assert checked.history[0]["smoothing_gain"] > 0
    assert not checked.converged
    unchecked = ceemx.fit(
        guess, data, x0, solver=ceemx.JointLM(rtol=0.9, check_smoothing=False), max_epochs=1,
        diagnose=False,
    )  # fmt: skip
    assert unchecked.converged
    assert unchecked.history[0]["smoothing_gain"] == 0.0
    # The check's states are a smoothing pass at the end θ: J rose by the recorded gain.
    gain = checked.history[0]["smoothing_gain"]
    assert checked.history[0]["J"] == pytest.approx(unchecked.history[0]["J"] + gain, rel=1e-9)
