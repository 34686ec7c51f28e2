"""The simulated friction case (:mod:`ceemx.datasets.friction_sim`): the simulator, its truth
model, and :func:`ceemx.fit_hybrid` called untouched closing the gap the user's physics leaves."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.datasets import friction_sim


@pytest.fixture(scope="module")
def short():
    return friction_sim.friction_positioning(seed=3, n_train=400, n_test=200)


def test_records_are_a_deterministic_function_of_the_seed(short):
    again = friction_sim.friction_positioning(seed=3, n_train=400, n_test=200)
    other = friction_sim.friction_positioning(seed=4, n_train=400, n_test=200)
    for a, b in ((short.train, again.train), (short.test, again.test)):
        np.testing.assert_array_equal(np.asarray(a.y), np.asarray(b.y))
        np.testing.assert_array_equal(np.asarray(a.u), np.asarray(b.u))
    assert not np.array_equal(np.asarray(short.train.y), np.asarray(other.train.y))
    assert short.train.y.shape == (1, 400, 1) and short.test.u.shape == (1, 200, 1)
    assert short.train.info is not None and short.train.info.dt == friction_sim.DT
    with pytest.raises(ValueError, match="too short"):
        friction_sim.friction_positioning(n_train=50)


def test_truth_model_steps_as_the_simulator(short):
    """The plant's states follow StribeckMass.truth()'s transition up to the simulated force
    disturbance alone (velocity residuals of FORCE_NOISE·dt/m, none on the position), and the
    record's y is the position plus the sensor noise."""
    truth = short.truth
    x = jnp.asarray(short.states["train"])
    u = jnp.asarray(short.train.u[0])
    step = jax.vmap(lambda xx, uu: truth.dynamics(xx, uu, 0))(x[:-1], u[:-1])
    r = np.asarray(step - x[1:])
    assert np.max(np.abs(r[:, 0])) < 1e-15
    sigma = friction_sim.FORCE_NOISE * friction_sim.DT / friction_sim.TRUE_PARAMETERS["mass"]
    assert 0.8 * sigma < r[:, 1].std() < 1.2 * sigma
    e = np.asarray(short.train.y[0, :, 0]) - np.asarray(x[:, 0])
    assert 0.8 * friction_sim.OBS_NOISE < e.std() < 1.2 * friction_sim.OBS_NOISE


def test_friction_law_and_the_physics_that_lacks_it():
    """F_f at rest is 0, at v ≫ ε it is the Stribeck level plus viscous; the user's physics
    (mass, viscous, offset) has no Coulomb or Stribeck term to learn."""
    p = friction_sim.TRUE_PARAMETERS
    args = (p["coulomb"], p["static"], p["stribeck_velocity"], p["smoothing"], p["viscous"])
    assert float(friction_sim.stribeck_friction(jnp.asarray(0.0), *args)) == 0.0
    v = 0.2  # ≫ v_s: Coulomb + viscous
    expected = p["coulomb"] + (p["static"] - p["coulomb"]) * math.exp(-((v / p[
        "stribeck_velocity"]) ** 2)) + p["viscous"] * v  # fmt: skip
    assert float(friction_sim.stribeck_friction(jnp.asarray(v), *args)) == pytest.approx(expected)
    assert friction_sim.stribeck_friction(v, *args, xp=math) == pytest.approx(expected)
    guess = friction_sim.ViscousMass.guess()
    assert {f for f in ("mass", "viscous", "offset") if hasattr(guess, f)} == {
        "mass", "viscous", "offset"
    }  # fmt: skip
    assert not hasattr(guess, "coulomb") and float(guess.mass) != p["mass"]


@pytest.mark.slow  # the procedure on 8,000 samples: ≈ 5–16 min on a loaded 2-core machine
def test_fit_hybrid_closes_most_of_the_friction_gap():
    """``fit_hybrid`` called as a user calls it (the physics at its guess, n_init, the term in
    the velocity equation; every option at its default) on a closed-loop record whose friction
    the physics lacks: on a test record with another reference, the hybrid closes ≥ 70 % of the
    gap between the physics' free-run error and the true plant's."""
    rec = friction_sim.friction_positioning(seed=0, n_train=TEST_SAMPLES, n_test=5000)
    sel = ceemx.fit_hybrid(rec.guess, rec.train, n_init=rec.n_init, dynamics=(1,))
    physics = ceemx.fit(rec.guess, rec.train, solver=ceemx.JointLM(), diagnose=False)

    def score(m):
        return float(ceemx.benchmark_score(m, rec.test, rec.n_init).rmse[0, 0])

    s = {
        "physics": min(score(physics.system), score(sel.physics.system)),
        "hybrid": score(sel.system),
        "true": score(rec.truth),
    }
    gap = (s["physics"] - s["hybrid"]) / (s["physics"] - s["true"])
    assert sel.best_epoch > 0 and sel.refit, sel.summary()
    assert gap >= 0.7, (s, sel.summary())


#: Training samples of the slow test (the benchmark script uses the issue's 20,000).
TEST_SAMPLES = 8000
