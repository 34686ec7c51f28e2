"""Profile-likelihood intervals (``FitResult.profile``) against answers known in closed form.

Each fit is a :class:`ceemx.FitResult` built at the exact maximum (computed here in NumPy), so
the file compiles the refits' programs only:

- a linear-Gaussian model under Laplace EM (exact EM there): the profile interval of A equals
  the brute-force profile of the exact Kalman log-likelihood, C maximised;
- a model whose J is quadratic in (x, θ) jointly: the profile interval of an entry of its
  unconstrained offsets is the Wald interval; of its positive gain, estimate ± q·SE in natural
  units, which the summary's rule prints (the Wald interval of z = softplus⁻¹(b) is skewed);
- that gain within its standard error of 0: the profile reaches the bound, the interval stays
  inside it, its upper end is estimate + q·SE (the Wald interval's is far out).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array
from kalman_em_reference import kalman_smoother
from scipy.optimize import minimize, minimize_scalar, root_scalar

import ceemx
from ceemx.identification.analysis.summary import parameter_rows
from ceemx.identification.problem import FitProblem
from ceemx.lib.results import RESULTS, select

jax.config.update("jax_enable_x64", True)

Q95 = 1.959963984540054  # √χ²₁(0.95)


def _result(system, data, states, solver, trainable) -> ceemx.FitResult:
    """A converged result of ``solver`` at (system, states), as ``fit`` returns it."""
    problem, theta = FitProblem.create(system, data, trainable=trainable)
    B = states.shape[0]
    status = select(jnp.ones((B,), bool), RESULTS.successful, RESULTS.nonfinite)
    return ceemx.FitResult(
        system, states, status, [], True, solver, 0.0,
        problem=problem, theta=theta, weights=jnp.ones((B,)),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# J quadratic in (x, b, d): x_{t+1} = 0.8 x_t + b u_t + w, y_t = x_t + d + v (two outputs)
# --------------------------------------------------------------------------------------------

SW, SV, T = 0.1, 0.3, 40


class Offsets(ceemx.AbstractSystem):
    """x_{t+1} = 0.8 x_t + b u_t + w,  y_t = (x_t + d₀, x_t + d₁) + v: J quadratic in (x, b, d)."""

    b: Array = ceemx.param(positive=True)
    d: Array

    @property
    def state_dim(self):
        return 1

    @property
    def obs_dim(self):
        return 2

    @property
    def input_dim(self):
        return 1

    def dynamics(self, x, u, t):
        return 0.8 * x + self.b * u

    def observe(self, x, u, t):
        return x + self.d


def _offsets(b: float, seed: int):
    """The JointLM result at the maximum of J, and the exact (estimate, SE) of each parameter.

    J's maximiser is the least-squares solution of the whitened residuals, linear in
    (x_1..x_T, b, d); its covariance is that solution's.
    """
    d = jnp.asarray([0.5, -0.3])
    true = Offsets(jnp.asarray(b), d, process_noise=SW, obs_noise=SV)
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    u = jax.random.normal(k1, (1, T, 1))
    _, data = ceemx.simulate(true, k2, jnp.zeros((1, 1)), T, u)
    y, uu, m = np.asarray(data.y)[0], np.asarray(u)[0, :, 0], true.obs_dim
    rows, rhs = [], []
    for t in range(T - 1):  # (x_{t+1} − 0.8 x_t − b u_t) / σ_w
        r = np.zeros(T + 1 + m)
        r[t + 1], r[t], r[T] = 1.0, -0.8, -uu[t]
        rows.append(r / SW)
        rhs.append(0.0)
    for t in range(T):  # (y_t − x_t − d) / σ_v
        for i in range(m):
            r = np.zeros(T + 1 + m)
            r[t], r[T + 1 + i] = 1.0, 1.0
            rows.append(r / SV)
            rhs.append(y[t, i] / SV)
    A = np.asarray(rows)
    v = np.linalg.lstsq(A, np.asarray(rhs), rcond=None)[0]
    se = np.sqrt(np.diagonal(np.linalg.inv(A.T @ A))[T:])
    fitted = Offsets(jnp.asarray(v[T]), jnp.asarray(v[T + 1 :]), process_noise=SW, obs_noise=SV)
    states = jnp.asarray(v[:T].reshape(1, T, 1))
    res = _result(fitted, data, states, ceemx.JointLM(), lambda s: (s.b, s.d))
    names = ["b", *(f"d[{i}]" for i in range(m))]
    return res, {n: (v[T + i], se[i]) for i, n in enumerate(names)}


def test_quadratic_objective_profile_is_the_wald_interval():
    """d enters J quadratically: the profile of ``d[1]`` (an entry of an array, held in θ without
    a gradient while ``d[0]`` learns) is its Wald interval. b too, in natural units, where the
    Wald interval (of z = softplus⁻¹(b)) is skewed: the summary's rule flags it and prints
    b̂ ± q·SE (b leaves θ: the ``trainable`` path)."""
    res, exact = _offsets(0.3, 5)
    d, se = exact["d[1]"]
    p = res.profile("d[1]")
    assert (p.lower_end, p.upper_end) == ("found", "found")
    assert p.estimate == pytest.approx(d, rel=1e-12)
    np.testing.assert_allclose(p.wald, (d - Q95 * se, d + Q95 * se), rtol=1e-8)
    np.testing.assert_allclose(p.interval, p.wald, atol=1e-3 * Q95 * se)
    for value, drop in p.points:  # every point computed lies on the parabola ((d − d̂)/SE)²
        assert drop == pytest.approx(((value - d) / se) ** 2, rel=1e-4, abs=1e-8)
    assert "profile interval" in str(p) and "Wald interval" in str(p)
    # the summary: b's profile interval (the rule: skewed at the Wald ends), d's Wald intervals
    rows, notes = parameter_rows(res)
    b, se_b = exact["b"]
    assert [(r.name, r.interval) for r in rows] == [("b", "profile"), ("d[0]", "Wald"),
                                                    ("d[1]", "Wald")]  # fmt: skip
    np.testing.assert_allclose((rows[0].lower, rows[0].upper), (b - Q95 * se_b, b + Q95 * se_b),
                               rtol=1e-4)  # fmt: skip
    assert "profile likelihood for b (skewed" in notes[-1]
    wald, _ = parameter_rows(res, intervals="wald")
    assert [r.interval for r in wald] == ["Wald"] * 3 and wald[1:] == rows[1:]
    assert rows[0].lower < wald[0].lower and rows[0].upper < wald[0].upper  # the Wald is too high
    with pytest.raises(KeyError, match=r"no trainable parameter named 'e'; .* b, d\[0\], d\[1\]"):
        res.profile("e")
    with pytest.raises(ValueError, match="`intervals` must be"):
        res.summary(intervals="likelihood")  # type: ignore[arg-type]


def test_positive_parameter_near_its_bound_reaches_the_bound(tmp_path):
    res, exact = _offsets(0.03, 3)
    b, se = exact["b"]
    assert 0.0 < b < Q95 * se  # the data put b within its error bar of the bound 0
    p = res.profile("b")
    assert p.lower_end == "bound" and p.lower == 0.0  # the interval stays inside b > 0
    assert p.upper_end == "found"
    assert p.upper == pytest.approx(b + Q95 * se, rel=1e-3)  # J is quadratic in the natural b
    assert min(p.points)[1] == pytest.approx((b / se) ** 2, rel=1e-3)  # the drop next to 0
    assert p.wald[0] > 0.0 and p.wald[1] > 2 * p.upper  # the Wald interval of z = softplus⁻¹(b)
    rows = {line.split()[0]: line for line in str(res.summary()).splitlines() if line}
    assert "profile, to bound" in rows["b"] and "Wald" in rows["d[0]"]
    assert "0 (the bound)" in str(p)
    # after Algorithm 1 (refits by JointLM, J the same): one more refit, at b̂, the same interval
    q = dataclasses.replace(res, solver=ceemx.Alternating()).profile("b")
    assert q.interval == pytest.approx(p.interval, rel=1e-6) and q.evaluations > p.evaluations
    # a fit that did not converge: no profile in the summary (no maximum to fall from)
    rows_nc, notes = parameter_rows(dataclasses.replace(res, converged=False))
    assert [r.interval for r in rows_nc] == ["Wald"] * 3 and "did not converge" in notes[-1]
    # the figure: the points computed, the threshold, the interval
    from ceemx.evaluation.plots import plot_profile

    fig = plot_profile(p)
    ax = fig.axes[0]
    np.testing.assert_allclose(np.asarray(ax.lines[0].get_xydata()), np.asarray(p.points))
    assert np.asarray(ax.lines[1].get_ydata())[0] == pytest.approx(Q95**2)
    legend = ax.get_legend()
    assert legend is not None and "(bound)" in " ".join(t.get_text() for t in legend.get_texts())
    assert plot_profile(p, tmp_path / "b.png").stat().st_size > 1000


# --------------------------------------------------------------------------------------------
# Linear-Gaussian, Laplace EM: the exact (Kalman) profile likelihood
# --------------------------------------------------------------------------------------------

LG = {"Q": 0.3, "R": 0.2, "mu0": 0.0, "P0": 1.0}


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


def _kalman_profile_interval(y, a_hat, c_hat):
    """The 95 % profile interval of a from the Kalman log-likelihood, c maximised (brute force)."""

    def profile(a):
        best: Any = minimize_scalar(
            lambda c: -_loglik(y, a, c, **LG),
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


# A second profile oracle; default: test_quadratic_objective_profile_is_the_wald_interval.
@pytest.mark.slow
def test_laplace_em_profile_is_the_kalman_likelihood_profile():
    """Linear-Gaussian, A and C learned by Laplace EM (exact EM): the profile interval of A is
    the brute-force profile of the exact (Kalman) log-likelihood over C, to 0.1 % of its
    half-width (it is 3·10⁻⁵ off; the Wald ends are 5–6 % off)."""
    prior = ceemx.GaussianPrior(
        jnp.asarray([LG["mu0"]]), ceemx.CholeskyGaussian(cov=jnp.asarray([[LG["P0"]]]))
    )

    def system(a, c):
        return ceemx.systems.LinearSystem(
            jnp.asarray([[a]]), jnp.asarray([[c]]),
            process_noise=LG["Q"] ** 0.5, obs_noise=LG["R"] ** 0.5, initial_prior=prior,
        )  # fmt: skip

    _, data = ceemx.simulate(system(0.7, 1.0), jax.random.PRNGKey(1), jnp.zeros((2, 1)), 40)
    y = np.asarray(data.y)[..., 0]
    best: Any = minimize(lambda v: -_loglik(y, v[0], v[1], **LG), [0.5, 0.8], method="BFGS",
                         options={"gtol": 1e-9})  # fmt: skip
    a_hat, c_hat = (float(v) for v in best.x)
    means = [
        kalman_smoother(yb[:, None], [[a_hat]], [[c_hat]], [[LG["Q"]]], [[LG["R"]]],
                        [LG["mu0"]], [[LG["P0"]]])["mean"]
        for yb in y
    ]  # fmt: skip
    res = _result(system(a_hat, c_hat), data, jnp.asarray(np.stack(means)), ceemx.LaplaceEM(),
                  lambda s: (s.A, s.C))  # fmt: skip
    p = res.profile("A[0,0]")
    assert p.objective == "Laplace evidence" and p.estimate == pytest.approx(a_hat, rel=1e-12)
    lo, hi = _kalman_profile_interval(y, a_hat, c_hat)
    assert (p.lower_end, p.upper_end) == ("found", "found")
    half = 0.5 * (hi - lo)
    assert abs(p.lower - lo) < 1e-3 * half and abs(p.upper - hi) < 1e-3 * half
    assert abs(p.wald[0] - lo) > 0.02 * half  # the quadratic model is visibly off


@pytest.mark.slow  # compiles the JointLM iteration of the whole problem (≈ 3 s)
def test_profile_of_a_fit_stopped_short_falls_from_the_maximum():
    """A fit that stopped away from the maximum (b 30 % off, not converged): the profile refits to
    the maximum first, and its interval is the one at the maximum (b̂ + q·SE above)."""
    res, exact = _offsets(0.03, 3)
    b, se = exact["b"]
    moved = eqx.tree_at(lambda s: s.b, res.system, jnp.asarray(1.3 * b))
    early = dataclasses.replace(res, system=moved, theta=res.problem.theta_of(moved),
                                converged=False)  # fmt: skip
    p = early.profile("b")
    assert p.estimate == pytest.approx(1.3 * b)
    assert p.upper == pytest.approx(b + Q95 * se, rel=1e-3) and p.lower_end == "bound"
    assert "was not the maximum" in " ".join(p.notes)
