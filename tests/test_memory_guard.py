"""Work whose dense arrays cannot fit in memory is refused before any compute, with the way out.

The machine's memory is patched down to 256 bytes so the small test problems "do not fit".
"""

import jax
import numpy as np
import pytest

import ceemx
from ceemx.infra import memory as _memory
from ceemx.systems import CoupledLorenz, initial_states, random_observation_matrix


@pytest.fixture
def tiny_memory(monkeypatch):
    monkeypatch.setattr(_memory, "physical_memory", lambda: 256)


@pytest.fixture(scope="module")
def problem():
    C = random_observation_matrix(jax.random.PRNGKey(0), 1, m=2)
    true = CoupledLorenz([10.0], [28.0], [8.0 / 3.0], C, process_noise=0.1, obs_noise=0.5)
    x1 = initial_states(jax.random.PRNGKey(1), 2, 1)
    states, data = ceemx.simulate(true, jax.random.PRNGKey(2), x1, 16)
    guess = CoupledLorenz([9.0], [27.0], [2.5], C, process_noise=0.1, obs_noise=0.5)
    return guess, states, data


def test_physical_memory_is_known_here():
    total = _memory.physical_memory()
    assert total is None or total > 2**26


def test_check_fits_passes_small_and_refuses_large():
    _memory.check_fits("a small array", 1024, "no advice needed")
    with pytest.raises(ValueError, match=r"huge arrays need about .* GiB.*; do less"):
        _memory.check_fits("huge arrays", 1e30, "do less")


def test_lm_learner_refuses_matrices_that_do_not_fit(problem, tiny_memory):
    """The learning step (Algorithm 1's M-step; ``ceemx.learn`` alone: no smoother to compile)."""
    guess, states, data = problem
    trainable = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731
    with pytest.raises(ValueError, match="LMLearner.*Gauss–Newton.*LBFGSLearner"):
        ceemx.learn(guess, states, data, ceemx.LMLearner(), trainable=trainable)


@pytest.mark.slow  # compiles an L-BFGS learning step (≈ 3 s)
def test_matrix_free_learner_is_not_refused(problem, tiny_memory):
    guess, states, data = problem
    trainable = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731
    new, _, _ = ceemx.learn(
        guess, states, data, ceemx.LBFGSLearner(max_steps=5), trainable=trainable
    )
    assert np.isfinite(float(new.sigma[0]))


def test_joint_method_refuses_a_border_that_does_not_fit(problem, tiny_memory):
    guess, states, data = problem
    with pytest.raises(ValueError, match="JointLM's linearisation.*Alternating"):
        ceemx.fit(
            guess,
            data,
            states,
            solver=ceemx.JointLM(),
            trainable=lambda s: (s.sigma, s.rho, s.beta),
            max_epochs=1,
            progress=False,
        )


@pytest.mark.parametrize("solver", ["joint", "alternating"])
def test_fit_refuses_before_any_compute(problem, tiny_memory, monkeypatch, solver):
    """Through ``fit``, the guard refuses before the start states are computed (no x_init: the
    warm start would smooth first) and before the first learning step, for both solvers."""
    from ceemx.identification import initialize

    def no_warm_start(*args, **kwargs):
        raise AssertionError("the warm start ran before the memory guard")

    monkeypatch.setattr(initialize, "warm_start_states", no_warm_start)
    guess, _, data = problem
    solver = ceemx.JointLM() if solver == "joint" else ceemx.Alternating()
    with pytest.raises(ValueError, match="more than this machine.s"):
        ceemx.fit(guess, data, solver=solver, trainable=lambda s: (s.sigma, s.rho, s.beta))
