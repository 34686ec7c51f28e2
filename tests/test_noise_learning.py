"""Noise without guessing: estimate_noise (Laplace log-evidence in one factor per noise model) and
fit(..., noise="learn") — the answer must not depend on the user's noise guess."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.analysis.noise_estimate import (
    estimate_noise,
    noise_ratios,
    residual_moments,
)
from ceemx.systems import LinearSystem

A = jnp.array([[0.95, 0.1], [-0.1, 0.9]])
C = jnp.array([[1.0, 0.0]])
Q, R = 0.1, 0.2


def linear(q=Q, r=R):
    # strongly typed scales: every noise value below shares one compiled posterior program
    f64 = jnp.float64
    return LinearSystem(A, C, process_noise=jnp.asarray(q, f64), obs_noise=jnp.asarray(r, f64))


@pytest.fixture(scope="module")
def lin_data():
    _, data = ceemx.simulate(linear(), jax.random.PRNGKey(3), jnp.zeros((2, 2)), 200)
    return data


@pytest.fixture(scope="module")
def estimate_from_truth(lin_data):
    return estimate_noise(linear(), lin_data)[0]


def _std(noise):
    return float(np.sqrt(np.asarray(noise.covariance())[0, 0]))


@pytest.mark.slow
def test_laplace_ratios_are_one_at_the_truth(lin_data):
    # For a linear-Gaussian model the Laplace posterior is exact and the moments are EM's
    # statistic: at the truth the ratios are 1 up to sampling error (N ≈ 400 → SD ≈ 7 %).
    nm = residual_moments(linear(), lin_data)
    ratios = noise_ratios(linear(), nm)
    assert np.all(np.abs(ratios["process_noise"] - 1) < 0.3)
    assert np.all(np.abs(ratios["obs_noise"] - 1) < 0.3)


def test_moment_gradient_matches_the_evidence(lin_data):
    # ∂ log-evidence / ∂ log c = Σ_i N_i (ratio_i − 1): the gradient estimate_noise follows.
    system = linear(q=0.3 * Q, r=2.0 * R)
    nm = residual_moments(system, lin_data)
    ratios = noise_ratios(system, nm)
    g_proc = float(nm.moments["dyn_count"]) * float(np.sum(ratios["process_noise"] - 1))
    g_obs = float(np.sum(np.asarray(nm.moments["obs_count"]) * (ratios["obs_noise"] - 1)))
    h = 1e-4

    def ev(q, r):
        m = residual_moments(linear(q, r), lin_data, nm.states)
        return float(np.sum(m.log_evidence))

    fd_proc = (ev(0.3 * Q * np.exp(h), 2 * R) - ev(0.3 * Q * np.exp(-h), 2 * R)) / (2 * h)
    fd_obs = (ev(0.3 * Q, 2 * R * np.exp(h)) - ev(0.3 * Q, 2 * R * np.exp(-h))) / (2 * h)
    assert g_proc == pytest.approx(fd_proc, rel=1e-4)
    assert g_obs == pytest.approx(fd_obs, rel=1e-4)


@pytest.mark.parametrize(
    "q_fac, r_fac", [pytest.param(100.0, 1.0, marks=pytest.mark.slow), (0.01, 1.0)]
)
def test_estimate_noise_does_not_depend_on_the_guess(lin_data, estimate_from_truth, q_fac, r_fac):
    truth = estimate_from_truth
    est, _, _ = estimate_noise(linear(Q * q_fac, R * r_fac), lin_data)
    # one maximum, whatever the guess (to the optimiser's tolerance) ...
    assert _std(est.process_noise) == pytest.approx(_std(truth.process_noise), rel=1e-3)
    assert _std(est.obs_noise) == pytest.approx(_std(truth.obs_noise), rel=1e-3)
    # ... and it is the true noise up to sampling error (400 residuals per group)
    assert _std(est.process_noise) == pytest.approx(Q, rel=0.2)
    assert _std(est.obs_noise) == pytest.approx(R, rel=0.2)


def test_estimate_noise_leaves_the_flat_evidence_of_a_vanishing_scale(
    lin_data, estimate_from_truth
):
    # σ_w 10⁴× too small: the evidence is flat there (the output-error plateau: the states follow
    # the dynamics, all the noise is the observations'), and L-BFGS alone stopped at σ_w 1e-5
    # (139 nats below the maximum, measured). A decade step finds the slope again: without the
    # grid, the same maximum as from the truth.
    est, nm, _ = estimate_noise(linear(Q * 1e-4, R), lin_data, search=False)
    truth = estimate_from_truth
    assert _std(est.process_noise) == pytest.approx(_std(truth.process_noise), rel=1e-3)
    assert _std(est.obs_noise) == pytest.approx(_std(truth.obs_noise), rel=1e-3)


def test_learn_noise_validation(lin_data):
    with pytest.raises(ValueError, match="`noise` must be"):
        ceemx.fit(linear(), lin_data, noise="guess")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="LaplaceEM learns noise itself"):
        ceemx.fit(linear(), lin_data, noise="learn", solver=ceemx.LaplaceEM())
    with pytest.raises(ValueError, match="does not checkpoint"):
        ceemx.fit(linear(), lin_data, noise="learn", checkpoint="/tmp/ceemx-never-written")
    with pytest.raises(ValueError, match="max_evaluations"):
        estimate_noise(linear(), lin_data, max_evaluations=0)
    with pytest.raises(ValueError, match="fields"):
        estimate_noise(linear(), lin_data, fields=("initial_prior",))


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["joint", "alternate"])
def test_stiff_model_reaches_the_true_noise_optimum_from_any_guess(solver):
    # A stiff, partially observed 3-state model with a hidden internal force (tests/stiff_model.py),
    # θ started ±30 %, the noise guessed 100× off either way (process, observation or both).
    import stiff_model as sm

    _, data, _ = sm.simulate(jax.random.PRNGKey(0), B=2, T=1000)
    th0 = sm.perturbed(jax.random.PRNGKey(1))
    make_solver = {"joint": ceemx.JointLM, "alternate": ceemx.Alternating}[solver]
    ref = ceemx.fit(sm.make(th0), data, solver=make_solver(), max_epochs=300)
    assert ref.converged
    guesses = [(100, 100), (0.01, 0.01), (0.01, 1), (100, 1), (1, 100), (1, 0.01)]
    for pf, of in guesses if solver == "joint" else guesses[2:4]:
        guess = sm.make(th0, process_std=sm.PROCESS_STD * pf, obs_std=sm.OBS_STD * of)
        r = ceemx.fit(guess, data, solver=make_solver(), noise="learn", max_epochs=300)
        assert r.converged, (pf, of)
        for name in sm.TRUE:
            got, want = float(getattr(r.system, name)), float(getattr(ref.system, name))
            assert got == pytest.approx(want, rel=2e-3), (pf, of, name)
        # the learned factors are the true ones up to sampling error
        proc = np.asarray(r.noise_rounds[-1]["process_noise_std"]) / sm.PROCESS_STD
        obs = r.noise_rounds[-1]["obs_noise_std"][0] / sm.OBS_STD
        assert np.allclose(proc, proc[0]) and 0.8 < proc[0] < 1.25, (pf, of, proc)
        assert 0.8 < obs < 1.25, (pf, of, obs)
