"""Per-trajectory health: outliers excluded and named, ``converged``
never True without a finite fit, ``messages()`` consistent with ``converged``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from refusals import DATA, X0, decay, raises

import ceemx
from ceemx.experiments import common
from ceemx.identification.fitting.health import trajectory_health
from ceemx.identification.problem import FitProblem

jax.config.update("jax_enable_x64", True)

WHERE = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731


@pytest.fixture(scope="module")
def lorenz():
    true = common.true_lorenz(1, m=2, coupling=False)
    p = common.lorenz_problem(3, true, B=3, T=48, sigma_w=0.01, sigma_v=0.01, coupling=False)
    guess = ceemx.with_noise(p.init_system, process_noise=0.01, obs_noise=0.01)
    x0 = p.states + 0.1 * jax.random.normal(jax.random.PRNGKey(1), p.states.shape)
    return guess, p.data, x0


def theta(system):
    return np.array([float(system.sigma[0]), float(system.rho[0]), float(system.beta[0])])


@pytest.mark.slow
@pytest.mark.parametrize(
    "solver",
    [pytest.param(ceemx.JointLM(), marks=pytest.mark.slow), ceemx.Alternating()],
    ids=["joint", "alternate"],
)  # the joint case under slow (≈ 7 s of compilation); the exclusion logic is the driver's
def test_outlier_start_is_excluded_and_named(lorenz, solver):
    """A third trajectory started at 1e10 is excluded: θ equals the fit without it (1e-8)."""
    guess, data, x0 = lorenz
    bad = x0.at[2].set(1e10)
    with pytest.warns(UserWarning, match=r"trajectories 2 \(r = "):
        res = ceemx.fit(guess, data, bad, solver=solver, trainable=WHERE, max_epochs=30)
    ref = ceemx.fit(guess, data[:2], x0[:2], solver=solver, trainable=WHERE, max_epochs=30)
    np.testing.assert_allclose(theta(res.system), theta(ref.system), rtol=1e-8)
    assert res.excluded == (2,)
    assert res.messages()[2].startswith("excluded from the fit")
    np.testing.assert_array_equal(res.states[2], bad[2])  # returned as given
    np.testing.assert_allclose(res.states[:2], ref.states, rtol=1e-8, atol=1e-8)
    # Kept on request (the defect's behaviour, now opt-in and warned about) — but a start of
    # 1e10 is beyond any fit (r ≈ 1e137 > 1e16), refused even when kept.
    with (
        pytest.warns(UserWarning, match=r"trajectories 2 \(r = .*kept \(outliers='warn'\)"),
        pytest.raises(ValueError, match=r"too far from the data to fit: trajectory 2 \(r = "),
    ):
        ceemx.fit(guess, data, bad, solver=solver, trainable=WHERE, max_epochs=2, outliers="warn")


@pytest.mark.slow  # a fit of all three trajectories (the programs of B = 3, ≈ 3 s)
def test_outlier_kept_on_request(lorenz):
    """A start 10 off (r ≈ 2e6, 3000 × the others) is kept with outliers='warn', and it shows."""
    guess, data, x0 = lorenz
    solver = ceemx.Alternating()
    ref = ceemx.fit(guess, data[:2], x0[:2], solver=solver, trainable=WHERE, max_epochs=30)
    off = x0.at[2].add(10.0)
    # Warned at the start (kept) and by the end-of-fit noise check (an outlier?).
    with (
        pytest.warns(UserWarning, match="kept"),
        pytest.warns(ceemx.NoiseCheckWarning, match="trajectory 2 alone carries .* an outlier"),
    ):
        kept = ceemx.fit(
            guess, data, off, solver=solver, trainable=WHERE, max_epochs=2, outliers="warn"
        )
    assert kept.excluded == ()
    assert not np.allclose(theta(kept.system), theta(ref.system), rtol=1e-3)


def test_pure_noise_trajectory_is_flagged(lorenz):
    guess, data, x0 = lorenz
    rng = np.random.default_rng(0)
    y = np.asarray(data.y).copy()
    y[1] = 30.0 * rng.standard_normal(y[1].shape)
    noisy = ceemx.Trajectories(y)
    problem, th = FitProblem.create(guess, noisy, trainable=WHERE)
    health = trajectory_health(problem, th, x0)
    assert health.flagged.tolist() == [False, True, False]
    assert health.mean_square[1] > 100 * health.median


def test_health_needs_three_trajectories(lorenz):
    guess, data, x0 = lorenz
    problem, th = FitProblem.create(guess, data[:2], trainable=WHERE)
    health = trajectory_health(problem, th, x0[:2].at[1].set(1e5))
    assert not health.flagged.any()  # two cannot tell which one is odd


def test_every_trajectory_failing_is_an_error(lorenz):
    """Inputs that make J infinite for every trajectory: a clear error, not converged with J = 0."""
    guess, data, x0 = lorenz
    with pytest.raises(ValueError, match="no trajectory has a finite objective"):
        ceemx.fit(guess, data, jnp.full_like(x0, 1e200), trainable=WHERE, max_epochs=2)


@pytest.mark.slow
def test_messages_follow_converged(lorenz):
    """The driver's per-trajectory messages (Alternating on two trajectories: the programs of the
    outlier test's reference fit)."""
    guess, data, x0 = lorenz
    solver = ceemx.Alternating()
    # One epoch is not a fit whose residuals say anything about the noise: no noise check.
    res = ceemx.fit(
        guess, data[:2], x0[:2], solver=solver, trainable=WHERE, max_epochs=1, diagnose=False
    )
    assert not res.converged
    # one message per trajectory
    assert all(m.startswith("stopped before convergence") for m in res.messages()[:2])
    done = ceemx.fit(guess, data[:2], x0[:2], solver=solver, trainable=WHERE, max_epochs=100)
    assert done.converged and done.messages() == ["converged", "converged"]
    with pytest.raises(ValueError, match="outliers"):
        ceemx.fit(guess, data, x0, trainable=WHERE, outliers="drop")


# --- no converged=True from a start too far from the data ---------------------------------------


def test_absurd_start_is_refused():
    """Every start at 1e10: J ≈ −1e21 here (−2.55e67 on Lorenz), which 'converged' in 2 epochs."""
    with raises(ValueError, "the start is too far from the data to fit: trajectories 0 (r = "):
        ceemx.fit(decay(), DATA, np.full(X0.shape, 1e10))


def test_nonfinite_start_is_refused_with_outliers_kept():
    with raises(ValueError, "no trajectory has a finite objective at the start"):
        ceemx.fit(decay(), DATA, np.full(X0.shape, 1e200), outliers="keep")
