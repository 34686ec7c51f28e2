"""Residual and noise diagnostics: the end-of-fit noise check warns when the
assumed noise is inconsistent with the residuals, and ``FitResult.diagnostics()`` reports noise
ratios, the EM noise estimate and the EKF prediction-error tests.

One small linear-Gaussian problem (n = 2, m = 1, p = 1, σ_w = 0.1, σ_v = 0.03, B = 2, T = 200),
fitted with one compiled program (JointLM, B trainable, started at the true states): every fit
below differs only in array values (strongly typed, so none retraces).
"""

import dataclasses
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.evaluation import plots
from ceemx.identification.analysis.diagnostics import (
    PredictionErrorCheck,
    _extremes,
    prediction_error_check,
    residual_diagnostics,
)
from ceemx.identification.analysis.noise_check import LOWER, chi2_band, noise_check
from ceemx.identification.analysis.summary import _facts as summary_facts

jax.config.update("jax_enable_x64", True)

A = np.array([[0.95, 0.1], [-0.1, 0.9]])
B_IN = np.array([[0.0], [0.5]])
C = np.array([[1.0, 0.0]])
Q_STD, R_STD = 0.1, 0.03
B, T = 2, 200
simulate = eqx.filter_jit(ceemx.simulate)


def model(q_std=Q_STD, a=A):
    f64 = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731 — strong types: one program
    return ceemx.systems.LinearSystem(
        f64(a), f64(C), f64(B_IN), process_noise=f64(q_std), obs_noise=f64(R_STD)
    )


def record(seed):
    u = jnp.repeat(jax.random.normal(jax.random.PRNGKey(1000 + seed), (B, T // 10, 1)), 10, 1)
    x, data = simulate(model(), jax.random.PRNGKey(seed), jnp.zeros((B, 2)), T, u)
    return data, x


def fit(data, x, q_std=Q_STD, a_wrong=None, **kw):
    base = model(q_std) if a_wrong is None else a_wrong
    guess = eqx.tree_at(lambda s: s.B, base, jnp.asarray(1.3 * B_IN))
    return ceemx.fit(
        guess, data, x, solver=ceemx.JointLM(), trainable=lambda s: s.B, max_epochs=30, **kw
    )


@pytest.fixture(scope="module")
def problem():
    data, x = record(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the true noise: no warning
        res = fit(data, x)
    return data, x, res


@pytest.mark.slow
def test_true_noise_is_consistent_and_rho_is_chi2(problem):
    """ρ = Σ r̂² / (N_res − B·T·n − P) has mean 1 and sd √(2/d): a few records, no warning.

    The model is linear in (x, B) jointly, so Σ r̂² at the joint optimum is exactly χ²(d).
    """
    _, _, res = problem
    check = res.noise_check
    assert res.converged and check is not None and check.consistent
    assert check.message is None and not any("assumed noise" in m for m in res.messages())
    d = B * ((T - 1) * 2 + T) - B * T * 2 - 2
    assert check.dof == d and check.residuals == B * ((T - 1) * 2 + T)
    rhos = [check.ratio]
    for seed in range(1, 8):
        data, x = record(seed)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            rhos.append(fit(data, x).noise_check.ratio)  # pyright: ignore[reportOptionalMemberAccess]
    sd = np.sqrt(2.0 / d)
    assert np.all(np.abs(np.array(rhos) - 1.0) < 4 * sd), rhos
    assert abs(np.mean(rhos) - 1.0) < 3.5 * sd / np.sqrt(len(rhos)), rhos


def test_process_noise_too_tight_warns(problem):
    data, x, _ = problem
    with pytest.warns(UserWarning, match="too tight.*observation residuals carry it") as rec:
        res = fit(data, x, q_std=Q_STD / 10)  # 100× too tight in variance
    assert "noise='learn'" in str(rec[0].message) and "estimate_noise" in str(rec[0].message)
    assert res.noise_check is not None and res.noise_check.ratio > 4
    assert res.messages()[-1] == res.noise_check.message


def test_process_noise_too_loose_warns(problem):
    data, x, _ = problem
    with pytest.warns(UserWarning, match="too loose") as rec:
        res = fit(data, x, q_std=Q_STD * 10)  # 100× too loose in variance
    assert "the process residuals" in str(rec[0].message)
    assert res.noise_check is not None and res.noise_check.ratio < LOWER


def test_diagnose_false_skips_the_check(problem):
    data, x, _ = problem
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fit(data, x, q_std=Q_STD / 10, diagnose=False)
    assert res.noise_check is None and not any("assumed noise" in m for m in res.messages())


def test_noise_check_bands_and_hand_built_results(problem):
    _, _, res = problem
    assert noise_check(ceemx.with_noise(res.system, obs_noise=ceemx.StudentT(0.03, 4.0, 1)),
                       res.problem.data, res.states) is None  # fmt: skip
    lo, hi = chi2_band(10.0)  # small d.o.f.: the χ² quantiles widen the band
    assert lo < 0.2 and hi > 2.5
    hand = ceemx.FitResult(res.system, res.states, res.status, [], True, res.solver, 0.0)
    assert hand.noise_check is None and len(hand.messages()) == B


@pytest.mark.slow
def test_diagnostics_pass_at_the_truth_with_laplace_ratios_near_one(problem, tmp_path):
    _, _, res = problem
    diag = res.diagnostics()
    assert diag.ok, diag.summary()
    for name in ("process_noise", "obs_noise"):
        np.testing.assert_allclose(diag.noise_ratios[name], 1.0, atol=0.25)
        assert diag.estimated_std is not None
        np.testing.assert_allclose(diag.estimated_std[name], diag.assumed_std[name], rtol=0.2)
    np.testing.assert_allclose(diag.nis, 1.0, atol=4 * np.sqrt(2 / (B * T)))
    assert diag.white.all() and diag.independent.all()
    assert diag.autocorrelation.shape == (1, 26) and diag.cross_correlation.shape == (1, 1, 51)
    assert "no problem found" in diag.summary() and "rho = " in diag.summary()
    path = plots.plot_residual_diagnostics(diag, tmp_path / "diag.png")
    assert path.stat().st_size > 0


@pytest.mark.slow
def test_whiteness_flags_missing_dynamics(problem):
    """The model with the wrong transition matrix: correlated one-step prediction errors."""
    data, x, _ = problem
    diag = residual_diagnostics(model(a=0.5 * A), data, x, estimate=False)
    assert not diag.white[0] and diag.box_pierce_p[0] < 1e-6
    assert any("correlated at lags 1" in p and "misses dynamics" in p for p in diag.problems)


def test_the_summary_says_whether_the_one_step_errors_are_white(problem):
    """Its row is the diagnostics' Box–Pierce test: white at the truth, not with A wrong."""
    data, x, res = problem
    check = prediction_error_check(res)
    assert check is not None and check.white and check.lags == 25
    assert dict(summary_facts(res))["one-step errors"].startswith("white (Box–Pierce")
    wrong = eqx.tree_at(lambda s: s.A, res.system, jnp.asarray(0.5 * A))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the noise check: residuals above the assumed noise
        misfit = fit(data, x, a_wrong=wrong)
    bad = prediction_error_check(misfit)
    assert bad is not None and not bad.white and bad.p_values[0] < 1e-6
    row = dict(summary_facts(misfit))["one-step errors"]
    assert row.startswith("NOT white at output 1") and "local optimum" in row
    no_check = dataclasses.replace(misfit, noise_check=None)  # a fit(diagnose=False): no row
    assert "one-step errors" not in dict(summary_facts(no_check))
    untested = PredictionErrorCheck((float("nan"),), 25)  # a filter that diverged
    assert untested.white and str(untested).startswith("not tested")


def test_the_outlier_test_finds_the_largest_error_and_its_bonferroni_p():
    """Largest |ẽ| per output, where, and min(1, N·P(|Z| ≥ it)); missing samples left out."""
    rng = np.random.default_rng(0)
    z = rng.standard_normal((2, 300, 2))
    z[1, 57, 0] = 30.0  # a glitch on output 1
    z[0, 3, 1] = np.nan  # a missing sample on output 2
    ext = _extremes(z)
    assert ext.at[0] == (1, 57) and ext.size[0] == 30.0
    assert ext.p[0] == 600 * math.erfc(30.0 / math.sqrt(2.0)) and ext.p[0] < 1e-190
    n2 = 599  # output 2: the present samples only
    assert ext.size[1] == np.nanmax(np.abs(z[..., 1]))
    np.testing.assert_allclose(ext.p[1], min(1.0, n2 * math.erfc(ext.size[1] / math.sqrt(2))))
    assert ext.p[1] > 0.01  # Gaussian errors: no outlier
    assert _extremes(np.full((1, 5, 1), np.nan)).at == (None,)
    diverged = np.full((1, 5, 1), np.inf)  # a filter that diverged: no outlier claimed
    assert _extremes(diverged).at == (None,) and not _extremes(diverged).p[0] < 0.01
    check = PredictionErrorCheck((0.5, 0.5), 25, ext)
    assert check.outliers == (0,) and check.white
    assert "OUTLIER at output 1: record 2, step 58, 30 predicted SDs (p = " in str(check)
    assert str(check).startswith(str(PredictionErrorCheck((0.5, 0.5), 25)))


@pytest.mark.slow
def test_an_outlier_the_learned_noise_absorbed_is_named_where_it_is(problem):
    """One glitch of 10⁴ noise SDs: with σ_v inflated to absorb it (σ_v² = glitch² / N, what a
    learned noise does) the NIS and whiteness pass, the outlier test names its record and step."""
    data, x, res = problem
    glitch = 1e4 * R_STD
    y = np.asarray(data.y).copy()
    y[1, 57, 0] += glitch
    glitched = ceemx.Trajectories(y, data.u)
    f64 = jnp.float64
    absorbing = ceemx.systems.LinearSystem(*(f64(a) for a in (A, C, B_IN)),
        process_noise=f64(Q_STD), obs_noise=f64(glitch / np.sqrt(B * T)))  # fmt: skip
    diag = residual_diagnostics(absorbing, glitched, x, estimate=False)
    assert diag.largest_at[0] == (1, 57) and diag.largest[0] > 0.9 * np.sqrt(B * T)
    assert diag.largest_p[0] < 1e-50 and diag.white[0]
    assert any("an outlier" in p and "record 2, step 58" in p for p in diag.problems)
    clean = residual_diagnostics(model(), data, x, estimate=False)  # the truth: none
    assert clean.largest_p[0] > 0.01 and not any("outlier" in p for p in clean.problems)
    check = prediction_error_check(res)
    assert check is not None and check.outliers == ()


def test_diagnostics_name_the_wrong_scale(problem):
    """Too tight process noise: the noise estimate recovers the true scale and flags it."""
    data, x, _ = problem
    diag = residual_diagnostics(model(Q_STD / 100), data, x)
    assert diag.estimated_std is not None
    np.testing.assert_allclose(diag.estimated_std["process_noise"], Q_STD, rtol=0.2)
    assert not diag.ratio_ok["process_noise"].any() and diag.ratio_ok["obs_noise"].all()
    assert any(p.startswith("process_noise (state 1)") and "too tight" in p for p in diag.problems)
    assert diag.nis[0] > 4 and not diag.nis_ok[0]
    # One verdict per noise question: with a passing end-of-fit check beside the failing
    # component, the check's line, the report and the fit summary all say INCONSISTENT.
    assert diag.noise_verdict == "INCONSISTENT: process_noise state 1, process_noise state 2"
    _, _, res = problem
    assert res.noise_check is not None and res.noise_check.verdict == "consistent"
    both = dataclasses.replace(diag, noise_check=res.noise_check)
    report = str(both)  # print() gives the report, repr stays one line
    assert report == both.summary() and report.startswith("Residual diagnostics\nnoise check")
    assert "consistent" not in report.replace("INCONSISTENT", "").replace("inconsistent", "")
    assert "the overall rho, pooling every component, lies inside its band" in report
    assert repr(both) == f"ResidualDiagnostics(outputs=1, lags=25, problems={len(both.problems)})"
    facts = dict(summary_facts(res, both))
    assert facts["noise check"].endswith(both.noise_verdict)
    assert dict(summary_facts(res))["noise check"].endswith("): consistent")  # no diagnostics


def test_printed_fit_objects_show_their_values(problem):
    """Noise models, standard errors and the named estimates print numbers, not dtypes."""
    _, _, res = problem
    assert repr(res.system.obs_noise) == "DiagonalGaussian(scale=0.03, dim=1)"
    assert "B=[[0.5" not in repr(res.system) and "f64[" not in repr(res.system)
    se = res.standard_errors()
    b_se = np.asarray(se.B)
    assert f"B=[[{b_se[0, 0]:.6g}],\n" in repr(se) and "A=None" in repr(se)
    estimates = res.parameter_estimates()
    assert list(estimates) == ["B[0,0]", "B[1,0]"]
    value, error = estimates["B[1,0]"]  # still a pair
    assert (value, error) == (float(res.system.B[1, 0]), float(b_se[1, 0]))
    assert repr(estimates["B[1,0]"]) == f"Estimate(estimate={value:.6g}, std_error={error:.6g})"
    table = str(estimates).splitlines()
    assert table[0].split() == ["parameter", "estimate", "std.", "error"]
    assert table[2].split() == ["B[1,0]", f"{value:.6g}", f"{error:.3g}"]


@pytest.mark.slow
def test_laplace_em_with_learned_noise_does_not_warn(problem):
    """Both noise models learned from a 100× too tight start: recorded, consistent, silent."""
    data, x, _ = problem
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = ceemx.fit(
            model(Q_STD / 10),
            data,
            x,
            solver=ceemx.LaplaceEM(),
            trainable=lambda s: (s.B, s.process_noise, s.obs_noise),
            max_epochs=200,
        )
    check = res.noise_check
    assert check is not None and check.learned == ("process_noise", "obs_noise")
    assert check.message is None and abs(check.ratio - 1) < 4 * np.sqrt(2 / check.dof)
    np.testing.assert_allclose(res.system.process_noise.scale, Q_STD, rtol=0.2)
