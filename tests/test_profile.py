"""Profile-likelihood intervals (``FitResult.profile``) against answers known in closed form.

- a linear-Gaussian model under Laplace EM (exact EM there): the profile interval of A equals
  the brute-force profile of the Kalman log-likelihood (``kalman_em_reference``), C maximised;
- a model whose J is quadratic in (x, θ) jointly: the profile interval is the Wald interval;
- a positive parameter within its standard error of 0: the profile reaches the bound, its
  upper end is estimate + q·SE (the objective is quadratic in natural units), the Wald interval
  of the unconstrained coordinate is far wider.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array
from kalman_em_reference import kalman_smoother
from scipy.optimize import minimize_scalar, root_scalar

import ceemx

jax.config.update("jax_enable_x64", True)

Q95 = 1.959963984540054  # √χ²₁(0.95)


class Offset(ceemx.AbstractSystem):
    """x_{t+1} = 0.8 x_t + b u_t + w,  y_t = x_t + d + v: J is quadratic in (x, b, d) jointly."""

    b: Array = ceemx.param(positive=True)
    d: Array

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 1

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return 0.8 * x + self.b * u

    def observe(self, x, u, t):
        return x + self.d


def _offset_fit(b: float, seed: int, obs: float):
    true = Offset(jnp.asarray(b), jnp.asarray(0.5), process_noise=0.1, obs_noise=obs)
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    u = jax.random.normal(k1, (1, 40, 1))
    _, data = ceemx.simulate(true, k2, jnp.zeros((1, 1)), 40, u)
    start = Offset(jnp.asarray(b + 0.2), jnp.asarray(0.3), process_noise=0.1, obs_noise=obs)
    return ceemx.fit(start, data, solver=ceemx.JointLM(), max_epochs=30, progress=False)


def test_quadratic_objective_profile_is_the_wald_interval():
    res = _offset_fit(1.0, 0, 0.1)
    assert res.converged
    est, se = res.parameter_estimates()["d"]
    p = res.profile("d")
    assert (p.lower_end, p.upper_end) == ("found", "found")
    assert p.estimate == pytest.approx(est, rel=1e-12)
    np.testing.assert_allclose(p.wald, (est - Q95 * se, est + Q95 * se), rtol=1e-10)
    np.testing.assert_allclose(p.interval, p.wald, atol=1e-3 * Q95 * se)
    # every point computed lies on the parabola ((d − d̂)/SE)²
    for value, drop in p.points:
        assert drop == pytest.approx(((value - est) / se) ** 2, rel=1e-4, abs=1e-8)
    assert "profile interval" in str(p) and "Wald interval" in str(p)


def test_positive_parameter_near_its_bound_reaches_the_bound():
    res = _offset_fit(0.03, 5, 0.3)
    est, se = res.parameter_estimates()["b"]
    assert 0.0 < est < Q95 * se  # the data put b within its error bar of the bound 0
    p = res.profile("b")
    assert p.lower_end == "bound" and p.lower == 0.0  # the interval stays inside b > 0
    assert p.upper_end == "found"
    # J is quadratic in the natural b: the upper end is est + q·SE
    assert p.upper == pytest.approx(est + Q95 * se, rel=1e-3)
    assert p.wald[0] > 0.0 and p.wald[1] > 2 * p.upper  # the Wald interval of z = softplus⁻¹(b)
    rows = {line.split()[0]: line for line in str(res.summary()).splitlines() if line}
    assert "profile, to bound" in rows["b"] and "Wald" in rows["d"]


def _loglik(y, a, c, Q, R, mu0, P0) -> float:
    """The exact log-likelihood of scalar records ``y`` (B, T): a scalar Kalman filter."""
    total = 0.0
    for yb in y:
        m, P = mu0, P0
        for yt in yb:
            S = c * c * P + R
            e = yt - c * m
            total -= 0.5 * (np.log(2 * np.pi * S) + e * e / S)
            K = P * c / S
            m, P = a * (m + K * e), a * a * (1.0 - K * c) * P + Q
    return total


def _kalman_profile_interval(y, a_hat, c_hat, Q, R, mu0, P0):
    """The 95 % profile interval of a from the Kalman log-likelihood, c maximised (brute force)."""
    ref = kalman_smoother(y[0][:, None], [[a_hat]], [[c_hat]], [[Q]], [[R]], [mu0], [[P0]])
    assert _loglik(y[:1], a_hat, c_hat, Q, R, mu0, P0) == pytest.approx(ref["loglik"], rel=1e-12)

    def profile(a):
        best: Any = minimize_scalar(
            lambda c: -_loglik(y, a, c, Q, R, mu0, P0),
            bracket=(c_hat - 0.2, c_hat + 0.2),
            method="brent",
            tol=1e-10,
        )
        return -float(best.fun)

    top = profile(a_hat)
    drop = lambda a: 2.0 * (top - profile(a)) - Q95**2  # noqa: E731
    lo = root_scalar(drop, bracket=(a_hat - 0.5, a_hat), xtol=1e-7).root
    hi = root_scalar(drop, bracket=(a_hat, min(a_hat + 0.5, 0.999)), xtol=1e-7).root
    return lo, hi


def test_laplace_em_profile_is_the_kalman_likelihood_profile():
    """Linear-Gaussian, A and C learned by Laplace EM (exact EM): the profile interval of A is
    the brute-force profile of the exact (Kalman) log-likelihood over C, within 2 % of its
    half-width (it is 3·10⁻⁵ off; the Wald interval's ends are 5 % off)."""
    Q, R, mu0, P0 = 0.3, 0.2, 0.0, 1.0
    prior = ceemx.GaussianPrior(jnp.asarray([mu0]), ceemx.CholeskyGaussian(cov=jnp.asarray([[P0]])))

    def system(a, c):
        return ceemx.systems.LinearSystem(
            jnp.asarray([[a]]),
            jnp.asarray([[c]]),
            process_noise=Q**0.5,
            obs_noise=R**0.5,
            initial_prior=prior,
        )

    _, data = ceemx.simulate(system(0.7, 1.0), jax.random.PRNGKey(1), jnp.zeros((2, 1)), 40)
    res = ceemx.fit(
        system(0.5, 0.8),
        data,
        solver=ceemx.LaplaceEM(),
        trainable=lambda s: (s.A, s.C),
        max_epochs=200,
        progress=False,
        diagnose=False,
    )
    assert res.converged
    est = res.parameter_estimates()
    a_hat, c_hat = est["A[0,0]"][0], est["C[0,0]"][0]
    p = res.profile("A[0,0]")
    assert p.objective == "Laplace evidence" and p.estimate == pytest.approx(a_hat)
    lo, hi = _kalman_profile_interval(np.asarray(data.y)[..., 0], a_hat, c_hat, Q, R, mu0, P0)
    assert (p.lower_end, p.upper_end) == ("found", "found")
    half = 0.5 * (hi - lo)
    assert abs(p.lower - lo) < 1e-3 * half and abs(p.upper - hi) < 1e-3 * half
    assert abs(p.wald[0] - lo) > abs(p.lower - lo)  # closer than the quadratic model
