"""Noise without guessing: estimate_noise (Laplace log-evidence in one factor per noise model) and
fit(..., noise="learn") — the answer must not depend on the user's noise guess."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.analysis import noise_estimate
from ceemx.identification.analysis.noise_check import noise_check
from ceemx.identification.analysis.noise_estimate import (
    NoiseEstimateWarning,
    NoiseMoments,
    estimate_noise,
    noise_ratios,
    residual_moments,
)
from ceemx.identification.analysis.noise_floor import EVIDENCE_MARGIN
from ceemx.identification.fitting import noise_rounds
from ceemx.identification.fitting.result import FitResult
from ceemx.lib.results import RESULTS
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


@pytest.fixture(scope="module")
def clean_data():
    """The same record without observation noise (σ_v = 1e-12): the evidence rises as σ_v → 0."""
    _, data = ceemx.simulate(linear(r=1e-12), jax.random.PRNGKey(3), jnp.zeros((2, 2)), 200)
    return data


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


# ---------------------------------------------------------------------------------------------
# Learned noise that cannot collapse (analysis.noise_floor) and what the estimate says about it
# ---------------------------------------------------------------------------------------------


def _off():
    """The model with θ off (A × 0.8): at the start of a fit, the process noise absorbs the
    model error and the evidence rises as σ_v → 0."""
    f64 = jnp.float64
    return LinearSystem(
        0.8 * A, C, process_noise=jnp.asarray(Q, f64), obs_noise=jnp.asarray(R, f64)
    )


def test_observation_noise_is_held_at_the_quantum_of_quantised_data(clean_data):
    # An encoder's record: y on a grid of 0.05, no other observation noise, θ off. The
    # evidence's maximum lay below the grid (without the floor: σ_v at the box's lower edge,
    # R·e⁻¹²); the estimate is held at quantum/√12, and says so.
    quantised = ceemx.Trajectories(jnp.round(clean_data.y / 0.05) * 0.05, clean_data.u)
    with pytest.warns(NoiseEstimateWarning, match="quantum of y"):
        est, nm, _ = estimate_noise(_off(), quantised)
    assert _std(est.obs_noise) == pytest.approx(0.05 / np.sqrt(12), rel=1e-6)
    assert nm.floored == ("obs_noise",) and nm.degenerate == () and nm.at_edge == ()


def test_degenerate_observation_noise_is_held_at_the_evidence_margin(clean_data):
    # Continuous data without observation noise: the evidence keeps rising as σ_v → 0 (the
    # states interpolate the data). The estimate is the largest σ_v the data allow: its
    # evidence within the margin of the value at the box's lower edge (σ_v = R·e⁻¹²), and a
    # decade above it outside.
    with pytest.warns(NoiseEstimateWarning, match="largest the data allow"):
        est, nm, _ = estimate_noise(linear(), clean_data)
    sv = _std(est.obs_noise)
    assert nm.degenerate == ("obs_noise",) and sv > 1e-3
    q = _std(est.process_noise)
    edge = residual_moments(linear(q, R * np.exp(-12.0)), clean_data, nm.states).evidence
    above = residual_moments(linear(q, 10 * sv), clean_data, nm.states).evidence
    assert edge - EVIDENCE_MARGIN - 1e-6 <= nm.evidence
    assert above < edge - EVIDENCE_MARGIN


def test_estimate_noise_raises_its_box_above_the_guess_and_flags_its_last_edge(
    lin_data, estimate_from_truth
):
    # data 1e7× the guess's scale (data in μm, noise guessed in m), beyond the box (guess·e¹²
    # ≈ 1.6e5): the box is raised and the estimate is the truth's, 1e7× — it stopped at the
    # edge, 61× too small, "converged", before; data 1e150× lie beyond every raise (e^48):
    # flagged at the last edge
    for factor in (1e7, 1e-7):  # and 1e-7× (data in m, noise guessed in μm): lowered
        scaled = ceemx.Trajectories(lin_data.y * factor, lin_data.u)
        est, nm, _ = estimate_noise(linear(), scaled)
        assert nm.at_edge == ()
        for field in ("process_noise", "obs_noise"):
            want = factor * _std(getattr(estimate_from_truth, field))
            assert _std(getattr(est, field)) == pytest.approx(want, rel=1e-3)
    big = ceemx.Trajectories(lin_data.y * 1e150, lin_data.u)
    with pytest.warns(NoiseEstimateWarning, match="upper edge of its search box"):
        est, nm, _ = estimate_noise(linear(), big)
    assert set(nm.at_edge) == {"process_noise", "obs_noise"}
    top = 12.0 * (1 + noise_estimate.BOX_MOVES)
    assert _std(est.obs_noise) == pytest.approx(R * np.exp(top), rel=1e-9)


def test_noise_is_not_learned_from_data_without_observation_or_variation(lin_data):
    none = ceemx.Trajectories(lin_data.y, lin_data.u, jnp.zeros(lin_data.y.shape[:2], bool))
    zero = ceemx.Trajectories(jnp.zeros_like(lin_data.y), lin_data.u)
    constant = ceemx.Trajectories(jnp.full_like(lin_data.y, 3.5), lin_data.u)
    for data, what in [(none, "no observation"), (zero, "constant"), (constant, "constant")]:
        with pytest.raises(ValueError, match=what):
            estimate_noise(linear(), data)
        with pytest.raises(ValueError, match=what):
            ceemx.fit(linear(), data, solver=ceemx.JointLM(), noise="learn")


def test_noise_check_does_not_call_interpolating_states_consistent(lin_data):
    # σ_v collapsed (1e-6 against the record's 0.2) and the process noise loose enough to carry
    # every residual: ρ = 1.18 lies in the band, yet the states interpolate the data
    system = linear(q=0.25, r=1e-6)
    check = noise_check(system, lin_data, residual_moments(system, lin_data).states)
    assert check is not None and check.band[0] < check.ratio < check.band[1]
    assert check.interpolating and not check.consistent
    assert check.message is not None and "interpolate the data" in check.message
    assert "DEGENERATE" in check.summary()
    # every noise 100× too loose: all residuals are small, which is "too loose", not interpolation
    loose = linear(q=100 * Q, r=100 * R)
    check = noise_check(loose, lin_data, residual_moments(loose, lin_data).states)
    assert check is not None and check.ratio < check.band[0] and not check.interpolating
    assert check.message is not None and "too loose" in check.message


class _Rounds:
    """Stand-ins for a noise round's fit and estimate: a noise factor per estimate, a record."""

    def __init__(self, factors, degenerate=(), at_edge=(), converged=True):
        self.factors, self.degenerate, self.fitted_at = list(factors), degenerate, []
        self.at_edge, self.converged = at_edge, converged

    def estimate(self, system, data, states, **_):
        c = self.factors.pop(0)
        nm = NoiseMoments(
            {},
            states,
            jnp.zeros(2),
            jnp.ones(2, bool),
            degenerate=self.degenerate,
            at_edge=self.at_edge,
        )
        return linear(Q * c, R * c), nm, 1

    def run_fit(self, system, inputs, options):
        self.fitted_at.append(_std(system.process_noise))
        history = [{"epoch": 1, "time": 100.0, "J": 0.0}]
        return FitResult(
            system, inputs.states, RESULTS.successful, history, self.converged, options.solver, 0.0
        )


def test_noise_rounds_that_do_not_settle_say_so(monkeypatch, lin_data):
    # every estimate doubles the noise: the rounds stop unsettled after their bound. They warn,
    # the result is not converged, its system carries the last round's noise (the one reported),
    # and the summary gives every round's time, "(learned)" and the number of rounds.
    n = noise_rounds.MAX_NOISE_ROUNDS
    fake = _Rounds([2.0**k for k in range(n + 1)])
    monkeypatch.setattr(noise_rounds, "estimate_noise_prepared", fake.estimate)
    monkeypatch.setattr(noise_rounds, "run_fit", fake.run_fit)
    x0 = jnp.zeros((2, 200, 2))
    with pytest.warns(
        NoiseEstimateWarning, match=f"stopped after {n} rounds before the noise settled"
    ):
        r = ceemx.fit(linear(), lin_data, x0, solver=ceemx.JointLM(), noise="learn")
    assert not r.converged and len(r.noise_rounds) == n + 1
    assert _std(r.system.process_noise) == pytest.approx(r.noise_rounds[-1]["process_noise_std"][0])
    assert _std(r.system.process_noise) == pytest.approx(fake.fitted_at[-1])
    text = " ".join(r.summary().split())  # wrapped lines joined
    total = sum(round_["time"] for round_ in r.noise_rounds)
    assert f"{total:.3g} s in all ({n} noise rounds)" in text
    assert f"noise learned in {n} rounds" in text and "not settled" in text
    assert text.count("(learned)") == 2 and "(given)" not in text
    assert any("did not settle" in m for m in r.messages())


def test_rounds_whose_noise_held_but_whose_fit_never_converged_say_which(monkeypatch, lin_data):
    # the estimate never moves (change 0) but no round's fit converges: not "0 %, not settled",
    # which reads as a contradiction, but what held and what did not
    n = noise_rounds.MAX_NOISE_ROUNDS
    fake = _Rounds([1.0] * (n + 1), converged=False)
    monkeypatch.setattr(noise_rounds, "estimate_noise_prepared", fake.estimate)
    monkeypatch.setattr(noise_rounds, "run_fit", fake.run_fit)
    with pytest.warns(NoiseEstimateWarning, match="unsettled: the noise held, but the last "
                      "round's fit did not converge. The result") as caught:  # fmt: skip
        r = ceemx.fit(linear(), lin_data, jnp.zeros((2, 200, 2)), solver=ceemx.JointLM(),
                      noise="learn")  # fmt: skip
    assert not any("before the noise settled" in str(w.message) for w in caught)
    assert not r.converged
    text = " ".join(r.summary().split())
    assert "(last change 0 %; the noise held, its fit did not converge)" in text
    assert "not settled" not in text


def test_noise_the_data_do_not_determine_is_not_fitted_at(monkeypatch, lin_data):
    # every estimate's evidence is flat over the whole box (σ_v held at its upper edge): no fit
    # runs at one; the fit runs at the noise given, converges, and the result says the noise
    # was not learned
    fake = _Rounds([1e-3] * 7, degenerate=("obs_noise",), at_edge=("obs_noise",))
    monkeypatch.setattr(noise_rounds, "estimate_noise_prepared", fake.estimate)
    monkeypatch.setattr(noise_rounds, "run_fit", fake.run_fit)
    x0 = jnp.zeros((2, 200, 2))
    with pytest.warns(NoiseEstimateWarning, match="could not learn the noise"):
        r = ceemx.fit(linear(), lin_data, x0, solver=ceemx.JointLM(), noise="learn")
    assert fake.fitted_at == [pytest.approx(Q)] and r.converged
    assert _std(r.system.process_noise) == pytest.approx(Q)
    assert any("the noise was not learned" in m for m in r.messages())
    assert r.summary().count("(given)") == 2


def test_degenerate_estimate_after_a_converged_fit_is_fitted_at(monkeypatch, lin_data):
    # the start's estimate is degenerate (kept out: the first fit runs at the noise given); the
    # one after that fit converged is the data's (σ_v at its margin's upper end) and the next
    # round fits at it. Kept out, a guess 100× too tight stayed the fit's noise on records whose
    # process noise dominates, with intervals 100× too narrow.
    fake = _Rounds([1e-3, 2.0, 2.0], degenerate=("obs_noise",))
    monkeypatch.setattr(noise_rounds, "estimate_noise_prepared", fake.estimate)
    monkeypatch.setattr(noise_rounds, "run_fit", fake.run_fit)
    x0 = jnp.zeros((2, 200, 2))
    r = ceemx.fit(linear(), lin_data, x0, solver=ceemx.JointLM(), noise="learn")
    assert fake.fitted_at == [pytest.approx(Q), pytest.approx(2.0 * Q)] and r.converged
    assert _std(r.system.process_noise) == pytest.approx(2.0 * Q)
    assert r.noise_rounds[-1]["learned"] and r.noise_rounds[-1]["degenerate"] == ("obs_noise",)


def test_degenerate_estimate_after_a_fit_that_did_not_converge_is_not_fitted_at(
    monkeypatch, lin_data
):
    # θ still far off (no fit converges): every round fits at the noise given, and the result
    # says the noise was not learned and the rounds did not settle
    n = noise_rounds.MAX_NOISE_ROUNDS
    fake = _Rounds([1e-3] * (n + 1), degenerate=("obs_noise",), converged=False)
    monkeypatch.setattr(noise_rounds, "estimate_noise_prepared", fake.estimate)
    monkeypatch.setattr(noise_rounds, "run_fit", fake.run_fit)
    x0 = jnp.zeros((2, 200, 2))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = ceemx.fit(linear(), lin_data, x0, solver=ceemx.JointLM(), noise="learn")
    said = [str(w.message) for w in caught if w.category is NoiseEstimateWarning]
    assert any("could not learn the noise" in m for m in said)
    assert any(f"stopped after {n} rounds unsettled: the noise held" in m for m in said)
    assert fake.fitted_at == [pytest.approx(Q)] * n and not r.converged
