"""Learned noise that cannot collapse (ceemx.identification.analysis.noise_floor).

The floors' pieces against known answers (a quantised record's step, the upper end of an
evidence margin), then — slow — the record where a learned observation noise collapsed: a stiff,
partially observed Bouc–Wen model with a hidden hysteretic force (tests/bouc_wen.py), ±30 % start,
its position read by an encoder. Before the floors, ``fit(..., noise="learn")`` learned σ_v at
the search box's edge (1.1e-10 m against the encoder's 5e-8 step), reported converged after 6
unsettled rounds and free-ran 4.2e-5 m (the fixed nominal noise: 5e-9 m).
"""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.analysis.noise_estimate import NoiseEstimateWarning
from ceemx.identification.analysis.noise_floor import (
    EVIDENCE_MARGIN,
    margin_floor,
    output_resolution,
    plateau,
    top_margin,
)


def test_a_margin_from_an_interpolating_spike_is_measured_from_the_plateau_above_it():
    # −evidence as a Lorenz record showed it: a numerical spike 2.8 nats above the plateau at
    # the interpolating maximum z = −19.5 (σ_v = 3.6e-9), the plateau (0) up to z = −5.6
    # (σ_v = 3.6e-3), rising as (z + 5.6)² beyond. From the spike the margin holds σ_v at the
    # spike; from the plateau it ends where (z + 5.6)² = 1.92.
    def objective(z):
        return -2.8 if abs(z + 19.5) < 1e-9 else max(z + 5.6, 0.0) ** 2

    step = float(np.log(10.0))
    z_star, top = -19.5, 7.0
    spike, _ = top_margin(objective, z_star, objective(z_star), top, step)
    assert spike == z_star
    reference = plateau(objective, z_star, objective(z_star), top, step)
    assert reference == 0.0
    z, determined = top_margin(objective, z_star, reference, top, step)
    end = -5.6 + np.sqrt(EVIDENCE_MARGIN)
    assert determined and z <= end < z + step / 64
    # no point above the maximum: its own value
    assert plateau(objective, top, -1.0, top, step) == -1.0


def test_output_resolution_is_the_quantum_of_quantised_outputs():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(2, 300, 3))
    y[..., 0] = np.round(y[..., 0] / 0.05) * 0.05  # an ADC's step
    y[..., 2] = np.round(1e-3 * y[..., 2] / 5e-8) * 5e-8  # an encoder's, in metres
    # decimals written and read back (a CSV): the grid survives the rounding of the numbers
    y[0, :, 0] = [float(f"{v:.2f}") for v in y[0, :, 0]]
    mask = np.ones(y.shape, bool)
    mask[1, :, 1] = False
    res = output_resolution(ceemx.Trajectories(jnp.asarray(y), mask=jnp.asarray(mask)))
    assert res[0] == pytest.approx(0.05, rel=1e-9)
    assert np.isnan(res[1])  # continuous values lie on no grid: no floor
    assert res[2] == pytest.approx(5e-8, rel=1e-9)


def test_margin_floor_is_the_upper_end_of_the_margin():
    # −evidence flat below z = 0 (the degenerate plateau), rising as (z)² beyond: the margin
    # ends where z² = 1.92, to 1/64 of a decade
    def objective(z):
        return max(z, 0.0) ** 2

    step = float(np.log(10.0))
    z, determined = margin_floor(objective, -20.0, 0.0, 30.0, step)
    assert determined and z <= np.sqrt(EVIDENCE_MARGIN) < z + step / 64
    # flat all the way to the box's upper edge: not determined, the edge
    z, determined = margin_floor(lambda z: 0.0, -20.0, 0.0, 5.0, step)
    assert not determined and z == 5.0


def test_top_margin_passes_a_numerical_dip_that_stops_the_climb():
    # −evidence: its minimum at z = −18 (σ_v far below the data's noise, where the states
    # interpolate the data), a numerical dip of 5 nats over (−16, −13), within 0.5 nats again up
    # to z = −4, rising as (z + 4)² beyond. Climbing from the minimum stops at the dip; coming
    # down from the box's top finds the margin's real upper end, where 0.5 + (z + 4)² = 1.92.
    def objective(z):
        if z <= -18.0:
            return 0.0
        if -16.0 < z < -13.0:
            return 5.0
        return 0.5 + max(z + 4.0, 0.0) ** 2

    step = float(np.log(10.0))
    climbed, _ = margin_floor(objective, -18.0, 0.0, 10.0, step)
    assert climbed < -15.0
    z, determined = top_margin(objective, -18.0, 0.0, 10.0, step)
    top = -4.0 + np.sqrt(EVIDENCE_MARGIN - 0.5)
    assert determined and z <= top < z + step / 64
    # nothing above the maximum within the margin: the maximum itself
    z, determined = top_margin(lambda z: 0.0 if z <= 0 else 10.0, -1.0, 0.0, 10.0, step)
    assert determined and z == -1.0
    # within the margin at the box's top: not determined, the edge
    z, determined = top_margin(lambda z: 0.0, -1.0, 0.0, 10.0, step)
    assert not determined and z == 10.0


# ---------------------------------------------------------------------------------------------
# The collapse record (slow: each fit is a minute or more on one core)
# ---------------------------------------------------------------------------------------------

QUANTUM = 5e-8  # the encoder's step (m)


def _records(T, quantum=QUANTUM, obs_std=1e-12):
    import bouc_wen as bw

    system = bw.make(obs_std=obs_std)
    data, _ = bw.simulate(0, B=1, T=T, system=system, quantum=quantum)
    noiseless = bw.make(process_std=np.full(3, 1e-30), obs_std=1e-30)
    test, _ = bw.simulate(7, B=1, T=T, system=noiseless)
    return bw, data, test


def _free_run_rmse(system, test):
    _, y = ceemx.free_run(system, jnp.zeros((1, 3)), test.u)
    return float(np.sqrt(np.mean((np.asarray(y) - np.asarray(test.y)) ** 2)))


def _obs_std(system):
    return float(np.sqrt(np.asarray(system.obs_noise.covariance())[0, 0]))


@pytest.mark.slow
def test_learned_noise_does_not_collapse_on_the_hysteretic_record():
    # Continuous record (no encoder), observation noise 1e-9 m, JointLM, T = 1000. The evidence
    # at the start θ rises as σ_v → 0: fitted there, θ hardly moved (4 epochs, converged) and the
    # rounds crept to σ_v = 6e-11 m, free run 4.7e-5 m. The degenerate estimate is not fitted at.
    bw, data, test = _records(1000, quantum=None, obs_std=1e-9)
    guess = bw.make(bw.perturbed(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoiseEstimateWarning)
        r = ceemx.fit(guess, data, solver=ceemx.JointLM(), noise="learn", max_epochs=200)
    assert r.converged and r.noise_check is not None and r.noise_check.consistent
    assert 3e-10 < _obs_std(r.system) < 1e-8
    assert _free_run_rmse(r.system, test) < 1e-7
    assert r.noise_rounds[0]["degenerate"] == ("obs_noise",)  # the start's estimate


@pytest.mark.slow
@pytest.mark.parametrize(
    "solver, max_epochs", [(ceemx.JointLM(), 200), (None, 60)], ids=["joint", "default"]
)
def test_learned_noise_on_the_encoder_record_at_full_size(solver, max_epochs):
    # 2 048 samples, the position read by a 5e-8 m encoder. Whatever the solver, the learned σ_v
    # is never below what the encoder can show, and a fit that says converged free-runs within a
    # few encoder steps (a collapsed σ_v = 1.1e-10 m "converged" and free-ran at 4.2e-5 m).
    bw, data, test = _records(2048)
    guess = bw.make(bw.perturbed(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoiseEstimateWarning)
        warnings.simplefilter("ignore", ceemx.NoiseCheckWarning)
        r = ceemx.fit(guess, data, solver=solver, noise="learn", max_epochs=max_epochs)
    assert _obs_std(r.system) >= QUANTUM / np.sqrt(12) * (1 - 1e-9)
    if r.converged:  # collapsed: 4.2e-5 m; the estimates' last 0.1 % moves it by encoder steps
        assert _free_run_rmse(r.system, test) < 3e-7
    if solver is not None:  # JointLM: σ_v at the encoder's quantum, in 2 rounds (before: 5,
        # three of them at the degenerate estimate)
        assert r.converged and len(r.noise_rounds) - 1 <= 3
        assert _obs_std(r.system) == pytest.approx(QUANTUM / np.sqrt(12), rel=0.1)
