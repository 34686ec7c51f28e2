"""Laplace parameter uncertainty (ceemx.identification.analysis.uncertainty, FitResult.covariance /
standard_errors)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array

import ceemx
from ceemx.evaluation.report import estimate_table
from ceemx.identification.analysis.uncertainty import natural_jacobian, parameter_covariance
from ceemx.identification.problem import FitProblem
from ceemx.systems import CoupledLorenz, LinearSystem, initial_states

simulate = eqx.filter_jit(ceemx.simulate)


def _lorenz():
    k1, k2 = jax.random.split(jax.random.PRNGKey(3))
    true = CoupledLorenz(10.0, 28.0, 8 / 3, jnp.eye(3), process_noise=0.1, obs_noise=0.5)
    xs, data = simulate(true, k1, initial_states(k2, 2, 1), 12)
    x = xs + 0.05 * np.random.default_rng(0).standard_normal(xs.shape)
    return true, data, jnp.asarray(x)


def test_covariance_equals_dense_inverse_theta_block():
    """S⁻¹ is the θ-block of the inverse of the dense joint Gauss–Newton matrix."""
    system, data, x = _lorenz()
    problem, th = FitProblem.create(system, data, trainable=lambda s: (s.sigma, s.rho, s.beta))
    B, T, n = x.shape

    @eqx.filter_jit
    def dense(problem, x, th):
        def r(xflat, th):
            return ceemx.whitened_residuals(problem.build(th), xflat.reshape(x.shape), data)

        xflat = x.reshape(-1)
        return jax.jacfwd(lambda a, b: r(a, b).reshape(-1), 0)(xflat, th), jax.jacfwd(
            lambda a, b: r(a, b).reshape(-1), 1
        )(xflat, th)

    Jx, Jt = map(np.asarray, dense(problem, x, th))
    H = np.block([[Jx.T @ Jx, Jx.T @ Jt], [Jt.T @ Jx, Jt.T @ Jt]])
    expected = np.linalg.inv(H)[B * T * n :, B * T * n :]
    cov = np.asarray(parameter_covariance(problem, th, x, jnp.ones(B)))
    np.testing.assert_allclose(cov, expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())
    # A zero weight removes a trajectory: the same dense inverse from trajectory 0's residual
    # rows (whitened_residuals is (B, R), trajectory-major) and its states alone. The same compiled
    # program as above (only the weights' values differ; a one-trajectory problem would compile
    # the Schur complement again).
    R0, X0 = Jx.shape[0] // B, T * n
    Jx0, Jt0 = Jx[:R0, :X0], Jt[:R0]
    H0 = np.block([[Jx0.T @ Jx0, Jx0.T @ Jt0], [Jt0.T @ Jx0, Jt0.T @ Jt0]])
    expected0 = np.linalg.inv(H0)[X0:, X0:]
    cov0 = np.asarray(parameter_covariance(problem, th, x, jnp.asarray([1.0, 0.0])))
    np.testing.assert_allclose(cov0, expected0, rtol=1e-8, atol=1e-8 * np.abs(expected0).max())
    assert not np.allclose(cov0, cov, rtol=1e-2)  # the second trajectory did count above


def _scalar_data(key, a, B, T):
    true = LinearSystem([[a]], [[1.0]], process_noise=0.5, obs_noise=0.1)
    k1, k2 = jax.random.split(key)
    _, data = simulate(true, k1, jax.random.normal(k2, (B, 1)), T)
    return true, data


@pytest.mark.slow  # a Monte Carlo spread over refits (≈ 4 s); the dense-inverse oracle stays
def test_standard_error_matches_monte_carlo_spread():
    """x_{t+1} = a x_t + w, y_t = x_t + v: the SE of â matches the spread of â over datasets."""
    a, B, T, R = 0.8, 8, 40, 30
    guess = LinearSystem([[0.5]], [[1.0]], process_noise=0.5, obs_noise=0.1)
    solver = ceemx.JointLM(rtol=1e-10)
    estimates, ses, res = [], [], None
    for key in jax.random.split(jax.random.PRNGKey(1), R):
        _, data = _scalar_data(key, a, B, T)
        res = ceemx.fit(
            guess,
            data,
            data.y,
            solver=solver,
            trainable=lambda s: s.A,
            max_epochs=50,
            progress=False,
            outliers="keep",
        )
        assert res.converged
        estimates.append(float(res.system.A[0, 0]))
        ses.append(float(res.standard_errors().A[0, 0]))
    spread = np.std(estimates, ddof=1)
    ratio = np.mean(ses) / spread
    assert 0.6 <= ratio <= 1.6, (ratio, spread, np.mean(ses))
    assert abs(np.mean(estimates) - a) < 3 * spread / np.sqrt(R) + 0.02
    assert res is not None
    table = estimate_table(res.parameter_estimates(), {"A[0,0]": a})
    assert "| A[0,0] |" in table and "±" in table
    assert estimate_table(res.parameter_estimates(), {".A[0,0]": a}) == table  # old key paths


class Decay(ceemx.AbstractSystem):
    """x_{t+1} = a x_t + w,  y_t = g x_t + v (a ∈ (0, 1), g > 0)."""

    a: Array = ceemx.param(lower=0.0, upper=1.0)
    g: Array = ceemx.param(positive=True)

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return self.a * x

    def observe(self, x, u, t):
        return self.g * x


@pytest.fixture(scope="module")
def decay():
    """JointLM on :class:`Decay` (4 × 30 steps; 30 epochs, not converged: a noise-check note)."""
    true = Decay(jnp.asarray(0.7), jnp.asarray(1.5), process_noise=0.3, obs_noise=0.1)
    k1, k2 = jax.random.split(jax.random.PRNGKey(5))
    xs, data = simulate(true, k1, jax.random.normal(k2, (4, 1)), 30)
    with pytest.warns(ceemx.NoiseCheckWarning):
        return ceemx.fit(
            true, data, xs, solver=ceemx.JointLM(rtol=1e-10), max_epochs=30, progress=False
        )


@pytest.mark.slow
def test_constrained_parameters_use_the_delta_method(decay):
    res = decay
    assert res.problem is not None
    cov = np.asarray(res.covariance())
    assert cov.shape == (2, 2) and np.all(np.isfinite(cov))
    jac = np.asarray(natural_jacobian(res.problem, res.theta))
    # d interval/dz = (1-0) σ(z)(1-σ(z)) = a(1-a); d softplus/dz = 1 - e^{-g}.
    a, g = float(res.system.a), float(res.system.g)
    np.testing.assert_allclose(jac, [a * (1 - a), 1 - np.exp(-g)], rtol=1e-10)
    se = res.standard_errors()
    np.testing.assert_allclose(
        [float(se.a), float(se.g)], jac * np.sqrt(np.diagonal(cov)), rtol=1e-12
    )
    np.testing.assert_allclose(
        res.covariance(natural=True), jac[:, None] * cov * jac[None, :], rtol=1e-12
    )
    # Non-trainable leaves are None.
    assert se.process_noise is None or all(
        leaf is None for leaf in jax.tree_util.tree_leaves(se.process_noise)
    )
    est = res.parameter_estimates()
    assert list(est) == ["a", "g"]  # names as written
    assert est["a"] == pytest.approx((a, float(se.a)))
    # The key paths of earlier versions still look up.
    assert ".a" in est and est[".a"] == est["a"] and est.get(".g") == est["g"]
    assert "missing" not in est and est.get(".missing") is None


def test_unidentifiable_parameter_gives_nan_and_a_warning():
    """H has no effect on a single attractor: S is singular."""
    system, data, x = _lorenz()
    problem, th = FitProblem.create(system, data, trainable=lambda s: (s.sigma, s.rho, s.beta, s.H))
    with pytest.warns(UserWarning, match="not positive definite") as record:
        cov = parameter_covariance(problem, th, x, jnp.ones(x.shape[0]))
    message = str(record[0].message)
    assert "H[0,0]" in message and "sigma" not in message  # names the culprits only
    assert cov.shape == (12, 12)
    assert np.all(np.isnan(np.asarray(cov)))
    # hold_weak: H held at its estimate, the covariance of σ, ρ, β conditional on it (as if H
    # were not trainable), NaN in H's rows and columns.
    with pytest.warns(UserWarning, match=r"conditional on H\[0,0\]"):
        held = np.asarray(
            parameter_covariance(problem, th, x, jnp.ones(x.shape[0]), hold_weak=True)
        )
    small, th3 = FitProblem.create(system, data, trainable=lambda s: (s.sigma, s.rho, s.beta))
    np.testing.assert_allclose(held[:3, :3], parameter_covariance(small, th3, x), rtol=1e-8)
    assert np.all(np.isnan(held[3:])) and np.all(np.isnan(held[:, 3:]))


# --------------------------------------------------------------------------------------------
# FitResult.summary / repr (ceemx.identification.analysis.summary), on the same fit
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_summary_names_estimates_intervals_and_constraints(decay):
    """One row per parameter as written; SE as parameter_estimates; forward(ẑ ± 1.96 σ_z)."""
    from ceemx.identification.analysis.summary import parameter_rows

    res = decay
    text = res.summary()
    assert isinstance(text, str) and repr(text) == str(text)  # shows as it reads at the prompt
    lines = text.splitlines()
    assert lines[0] == "Fit summary: JointLM, not converged after 30 epochs"
    rows, notes = parameter_rows(res, intervals="wald")
    assert [r.name for r in rows] == ["a", "g"] and notes == []
    assert [r.interval for r in rows] == ["Wald", "Wald"]
    assert "did not converge" in parameter_rows(res)[1][-1]  # no profile without a maximum
    est = res.parameter_estimates()
    cov = np.asarray(res.covariance())
    z = np.asarray(res.theta)
    for i, r in enumerate(rows):
        assert (r.estimate, r.se) == pytest.approx(est[r.name], rel=1e-12)
        step = 1.959963984540054 * np.sqrt(cov[i, i]) * np.eye(2)[i]
        ends = [float(res.problem.natural(jnp.asarray(z + s * step))[i]) for s in (-1, 1)]
        assert (r.lower, r.upper) == pytest.approx(tuple(ends), rel=1e-9)
    assert 0.0 < rows[0].lower < rows[0].estimate < rows[0].upper < 1.0  # inside the constraint
    assert rows[1].lower > 0.0
    row_a = next(line for line in lines if line.startswith("a "))
    assert "in (0, 1)" in row_a and f"{rows[0].estimate:.5g}" in row_a
    assert any(line.startswith("g ") and "> 0 (positive)" in line for line in lines)
    for label in ("process noise", "observation noise", "J (log-likelihood", "epochs", "status"):
        assert any(line.startswith(label) for line in lines), label
    assert "DiagonalGaussian, std 0.3 (given)" in text and "30, NOT converged" in text
    assert "noise check" in text and "INCONSISTENT" in text  # the fit's noise-check record
    assert "Messages:" in text and "the assumed noise is too loose" in text
    assert max(len(line) for line in lines) <= 100  # wrapped for a terminal


@pytest.mark.slow
def test_summary_markdown_and_repr(decay):
    res = decay
    md = res.summary("markdown", level=0.9)
    assert md.startswith("**Fit summary: JointLM")
    assert "| parameter | estimate | std. error | 90 % interval | constraint |" in md
    assert "| a | " in md and "| > 0 (positive) |" in md and "**Messages**" in md
    bare = res.summary(uncertainty=False, max_rows=1)
    assert "1 more parameters" in bare and " nan " in bare
    with pytest.raises((ValueError, TypeError)):  # TypeError: the tests' runtime type checks
        res.summary("html")  # type: ignore[arg-type]
    short = repr(res)
    assert short.startswith("FitResult(JointLM, not converged after 30 epochs, J = ")
    assert "a = " in short and "g = " in short and ".summary()" in short
    assert len(short.splitlines()) <= 3
