"""Laplace EM's end: an epoch that lowers the evidence is discarded; Newton's polish."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.analysis.uncertainty import evidence_covariance
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.laplace import LaplaceEM
from ceemx.identification.solvers.laplace_newton import POLISH_DECREMENT, newton_polish

jax.config.update("jax_enable_x64", True)


def _problem(T=40):
    rng = np.random.default_rng(3)
    A = np.array([[0.9, 0.2], [-0.15, 0.8]])
    x, y = np.zeros(2), np.zeros((2, T, 2))
    for b in range(2):
        x = rng.normal(size=2)
        for t in range(T):
            y[b, t] = x + 0.3 * rng.normal(size=2)
            x = A @ x + 0.2 * rng.normal(size=2)
    system = ceemx.systems.LinearSystem(
        jnp.asarray([[0.7, 0.0], [0.0, 0.6]]),
        jnp.eye(2),
        process_noise=ceemx.DiagonalGaussian(0.2, 2),
        obs_noise=ceemx.DiagonalGaussian(0.3, 2),
        initial_prior=ceemx.GaussianPrior(jnp.zeros(2), ceemx.CholeskyGaussian(cov=jnp.eye(2))),
    )
    return system, ceemx.Trajectories(jnp.asarray(y))


def _a(s):
    return s.A


def _fit(system, data, solver, epochs, states=None):
    return ceemx.fit(
        system,
        data,
        states,
        solver=solver,
        trainable=_a,
        max_epochs=epochs,
        outliers="keep",
        diagnose=False,
        progress=False,
    )


@pytest.mark.slow  # compiles a Laplace-EM fit (≈ 4 s)
def test_an_epoch_that_lowers_the_evidence_is_discarded(monkeypatch):
    """EM climbs the evidence; an epoch whose updates end lower (here made to, by 1e6 nats) is
    discarded: the fit stops at the previous θ and states, not converged, and says by how much."""
    system, data = _problem()
    advance = LaplaceEM._advance

    def falling(self, *args):
        new, record = advance(self, *args)
        record["log_evidence"] -= 1e6
        return new, record

    first = _fit(system, data, LaplaceEM(), 1)
    monkeypatch.setattr(LaplaceEM, "_advance", falling)
    out = _fit(first.system, data, LaplaceEM(), 5, first.states)
    assert out.epochs == 1 and not out.converged
    assert out.history[0]["evidence_fell"] > 1e6 - 10
    assert out.history[0]["log_evidence"] == pytest.approx(first.history[-1]["log_evidence"])
    np.testing.assert_array_equal(np.asarray(out.theta), np.asarray(first.theta))


@pytest.mark.slow  # a Laplace-EM fit to 1e-13 and 2 Newton tests (≈ 1.3 s)
def test_polish_returns_to_the_evidence_maximum():
    """From the maximum moved 0.5 standard errors along each axis, Newton's polish is back
    there to 1e-3 SE and certifies it; its first decrement is ½ s² of that offset (s² in the
    evidence covariance's metric; the evidence of a linear-Gaussian model is near-quadratic)."""
    system, data = _problem()
    solver = LaplaceEM(rtol=1e-13)
    best = _fit(system, data, solver, 500)
    assert best.converged
    problem, theta = FitProblem.create(best.system, data, trainable=_a)
    cov = np.asarray(evidence_covariance(problem, theta, best.states, smoother=solver.smoother))
    se = np.sqrt(np.diag(cov))
    off = 0.5 * se
    start = jnp.asarray(np.asarray(theta) + off)
    e = solver._posterior(problem, start, best.states)
    state = solver._state(problem, start, e, best.states, None)
    new, certified, record = newton_polish(solver, problem, state)
    assert certified is True and record["newton_steps"] >= 1
    np.testing.assert_allclose(np.asarray(new.theta), np.asarray(theta), atol=1e-3 * se.min())
    expected = 0.5 * off @ np.linalg.solve(cov, off)
    assert record["newton_decrements"][0] == pytest.approx(expected, rel=0.05)
    assert record["newton_decrements"][-1] <= POLISH_DECREMENT
    assert record["newton_gain"] == pytest.approx(expected, rel=0.05)
