"""The hysteresis case (``benchmarks/hysteresis_case.py``): the Bouc–Wen oscillator's simulator,
its truth model, and :func:`ceemx.fit_hybrid` called untouched on its linear physics."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
try:
    import hysteresis_case as case
finally:
    sys.path.pop(0)


@pytest.fixture(scope="module")
def short():
    return case.records(seed=1, n_train=300, n_test=200)


@pytest.mark.slow  # two periods of 8,192 samples at 20 RK4 substeps, twice: 3–7 s
def test_records_follow_the_plant_and_the_sensor(short):
    """The kept states follow the truth model's transition to rounding (no process noise), the
    outputs are the displacement plus the sensor noise, the input is the multisine of RMS 50 N,
    and the records are a deterministic function of the seed."""
    plant = case.truth()
    x = jnp.asarray(short.states["train"])
    u = jnp.asarray(short.train.u[0])
    step = jax.vmap(lambda xx, uu: plant.dynamics(xx, uu, 0))(x[:-1], u[:-1])
    np.testing.assert_allclose(np.asarray(step), np.asarray(x[1:]), rtol=0, atol=1e-9 * 50)
    e = np.asarray(short.train.y[0, :, 0]) - np.asarray(x[:, 0])
    assert 0.8 * case.OBS_NOISE < e.std() < 1.2 * case.OBS_NOISE
    period = case.multisine(np.random.default_rng(0))
    assert period.size == case.PERIOD and np.sqrt(np.mean(period**2)) == pytest.approx(50.0)
    spectrum = np.abs(np.fft.rfft(period))
    band = np.flatnonzero(spectrum > 1e-6 * spectrum.max()) * case.FS / case.PERIOD
    assert case.BAND[0] <= band.min() and band.max() <= case.BAND[1]
    again = case.records(seed=1, n_train=300, n_test=200)
    np.testing.assert_array_equal(np.asarray(again.test.y), np.asarray(short.test.y))


def test_hysteretic_force_follows_the_benchmark_law():
    """ż = α ẏ − β(γ |ẏ| z + δ ẏ |z|) (ν = 1) at a few states, and the user's physics has no z."""
    plant = case.truth()
    p = case.TRUE_PARAMETERS
    for y, v, z in ((1e-3, 0.1, 20.0), (-5e-4, -0.2, -35.0), (0.0, 0.05, -10.0)):
        f = np.asarray(plant.vector_field(jnp.array([y, v, z]), jnp.array([3.0]), 0.0))
        dz = p["alpha"] * v - p["beta"] * (p["gamma"] * abs(v) * z + p["delta"] * v * abs(z))
        acc = (3.0 - p["damping"] * v - p["stiffness"] * y - z) / p["mass"]
        np.testing.assert_allclose(f, [v, acc, dz], rtol=1e-12)
    assert case.guess().state_dim == 2


@pytest.mark.slow  # the procedure on 4,096 samples: ≈ 2–4 min on a loaded 2-core machine
def test_fit_hybrid_beats_the_linear_physics_on_the_hysteretic_plant():
    """``fit_hybrid`` called as a user calls it on a plant whose hysteretic force (a hidden
    state) the linear physics lacks: on a test record of another multisine the hybrid
    free-runs at least 10 % better than the better of the physics fitted on the whole record
    and the physics ``fit_hybrid`` returns, and the true plant better than both."""
    rec = case.records(seed=0, n_train=TEST_SAMPLES, n_test=TEST_SAMPLES)
    sel = ceemx.fit_hybrid(case.guess(), rec.train, n_init=case.N_INIT, dynamics=(1,))
    physics = ceemx.fit(case.guess(), rec.train, solver=ceemx.JointLM(), diagnose=False)
    s = {
        "physics": min(case.score_um(physics.system, rec.test),
                       case.score_um(sel.physics.system, rec.test)),
        "hybrid": case.score_um(sel.system, rec.test),
        "true": case.score_um(case.truth(), rec.test),
    }  # fmt: skip
    assert sel.best_epoch > 0 and sel.refit, sel.summary()
    assert s["true"] < s["hybrid"] < 0.9 * s["physics"], (s, sel.summary())


#: Training samples of the slow test (the benchmark script uses the benchmark's 8,192).
TEST_SAMPLES = 4096
