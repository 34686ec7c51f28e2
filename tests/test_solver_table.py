"""Every fit solver on every test problem: the table of tests/solver_table.py.

Each (solver, problem) pair runs once (``solver_table.run``: an uninterrupted fit with a
checkpoint, and a fit resumed from one of its checkpoints); the tests below
check, for every pair:

- the history entry the solver promises never to lower (``AbstractFitSolver.monotone``) rises;
- on the linear-Gaussian problems (complete and with missing data), the solver's known answer
  (``solver_table.ANSWERS``) against dense NumPy oracles, over the trajectories it can fit;
- every trajectory fitted is ``successful``; one no solver can fit (observations of 1e200, in
  the complete linear-Gaussian problem) is left out with a failure status and a warning;
- the resumed fit is the uninterrupted one, bit for bit;
- no function JAX traces is traced again in a later epoch, nor in the resumed fit's epochs (the
  problems start from a weakly typed θ leaf, which comes back strongly typed).

A new solver is tested by adding one row to ``solver_table.ROWS``. Pairs a row marks ``slow``
run with the slow tests.
"""

from __future__ import annotations

import collections

import numpy as np
import pytest
from kalman_em_reference import kalman_em
from solver_table import (
    LINEAR_GAUSSIAN,
    PROBLEMS,
    RESUME_AT,
    ROWS,
    LinearGaussian,
    ceemx_functions,
    least_squares_AC,
    log_likelihood,
    map_states,
    run,
)

import ceemx
from ceemx.lib.results import codes

TIMINGS = {"time", "smooth_time", "learn_time", "e_step_time", "m_step_time", "coarse_time"}


def _pairs(*, only=lambda row, name: True):
    """(row, problem name) of every pair that ``only`` keeps, marked ``slow`` where the row says."""
    return [
        pytest.param(
            row, name, id=f"{row.name}-{name}", marks=[pytest.mark.slow] if name in row.slow else []
        )
        for row in ROWS
        for name in row.problems
        if only(row, name)
    ]


PAIRS = _pairs()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Each pair's ``solver_table.run``, once per module."""
    done = {}

    def get(row, name):
        if (row.name, name) not in done:
            folder = tmp_path_factory.mktemp(f"{row.name}-{name}")
            done[row.name, name] = run(row, PROBLEMS[name](), folder)
        return done[row.name, name]

    return get


@pytest.mark.parametrize("row, name", _pairs(only=lambda row, name: row.solver.monotone))
def test_promised_entry_never_falls(runs, row, name):
    r = runs(row, name)
    key = row.solver.monotone
    values = r.result.history_array(key)
    assert np.all(np.isfinite(values))
    np.testing.assert_array_less(-1e-9 * np.abs(values[1:]), np.diff(values))
    if key == "J":
        assert values[0] >= r.result.initial_J - 1e-9 * abs(r.result.initial_J)


@pytest.mark.parametrize("row, name", _pairs(only=lambda row, name: name in LINEAR_GAUSSIAN))
def test_known_answer(runs, row, name):
    """On the trajectories fitted: a failing one must change nothing (``Problem.failing``)."""
    r, problem = runs(row, name), PROBLEMS[name]()
    ok = problem.fitted
    y, mask = np.asarray(problem.data.y)[ok], np.asarray(problem.data.mask)[ok]
    if row.answer == "optimum":
        assert r.result.converged
        lg = LinearGaussian.of(r.result.system)
        x = np.asarray(r.result.states)[ok]
        x_map = np.stack([map_states(lg, yb, mb) for yb, mb in zip(y, mask, strict=True)])
        np.testing.assert_allclose(x, x_map, atol=1e-4 * np.max(np.abs(x_map)))
        A, _ = least_squares_AC(lg, x, y, mask)
        np.testing.assert_allclose(lg.A, A, atol=1e-4)
        assert np.max(np.abs(lg.A - LinearGaussian.of(problem.start).A)) > 0.05  # θ moved
    elif row.answer == "evidence":
        for system, record in zip(r.systems, r.result.history, strict=True):
            exact = _log_likelihood(system, y, mask)
            np.testing.assert_allclose(record["log_evidence"], exact, rtol=1e-10)
    else:  # "likelihood estimate": each epoch's θ at its start
        starts = [problem.start, *r.systems[:-1]]
        diffs = [
            record["pf_log_likelihood"] - _log_likelihood(system, y, mask)
            for system, record in zip(starts, r.result.history, strict=True)
        ]
        assert np.max(np.abs(diffs)) < 4.0, diffs


def _log_likelihood(system, y, mask):
    lg = LinearGaussian.of(system)
    return sum(log_likelihood(lg, yb, mb) for yb, mb in zip(y, mask, strict=True))


def test_laplace_em_is_exact_em_on_a_linear_gaussian_model(runs):
    """Plain Laplace EM's θ and noise covariances after every epoch equal a textbook Kalman/RTS EM's
    (1e-8): the E-step is the exact posterior on a linear-Gaussian model."""
    row = next(r for r in ROWS if r.name == "LaplaceEM")
    r, problem = runs(row, "linear-gaussian"), PROBLEMS["linear-gaussian"]()
    s = LinearGaussian.of(problem.start)
    y = np.asarray(problem.data.y)[problem.fitted]
    ref = kalman_em(y, s.A, s.C, s.Q, s.R, s.mu0, s.P0, len(r.systems))
    for k, (system, want) in enumerate(zip(r.systems, ref, strict=True)):
        got = LinearGaussian.of(system)
        for name in ("A", "C", "Q", "R"):
            np.testing.assert_allclose(
                getattr(got, name), want[name], atol=1e-8, err_msg=f"{name}, epoch {k + 1}"
            )
    assert np.all(r.result.history_array("Q_gain") > -1e-8)  # the M-step raises Q


FAILED = {int(codes(s)) for s in (ceemx.RESULTS.nonfinite, ceemx.RESULTS.particle_failure)}


@pytest.mark.parametrize("row, name", PAIRS)
def test_statuses_name_what_failed_and_nothing_else(runs, row, name):
    """Every trajectory fitted is ``successful``; a failing one carries a failure status, is in
    every epoch's ``failed_trajectories`` and in a warning, and keeps its start states; a fit
    without one warns nothing."""
    r, problem = runs(row, name), PROBLEMS[name]()
    for result in (r.result, r.resumed):
        status = codes(result.status)
        assert status.shape == (problem.data.batch_size,)
        ok = status[problem.fitted] == codes(ceemx.RESULTS.successful)
        assert np.all(ok), result.messages()
        assert all(int(status[i]) in FAILED for i in problem.failing), result.messages()
        failed = list(problem.failing)
        assert all(h["failed_trajectories"] == failed for h in result.history)
        x_init = np.asarray(problem.x_init)[failed]
        np.testing.assert_array_equal(np.asarray(result.states)[failed], x_init)
        assert result.converged == result.history[-1]["converged"]
        assert [h["epoch"] for h in result.history] == list(range(1, result.epochs + 1))
    if problem.failing:
        assert any(str(failed) in w for w in r.warnings), r.warnings
    else:
        assert r.warnings == []


@pytest.mark.parametrize("row, name", PAIRS)
def test_resume_is_the_uninterrupted_fit(runs, row, name):
    """Resumed from the checkpoint of an epoch k (all its folder held while epoch k + 1 ran),
    the fit ends where the uninterrupted one does, bit for bit; each folder then holds its last
    epoch's checkpoint only."""
    r = runs(row, name)
    full, resumed = r.result, r.resumed
    files, meta = r.resumed_from
    k = r.resumed_at
    assert RESUME_AT <= k < full.epochs
    assert files == ["latest.json", f"state-{k}.eqx"]
    assert meta["epoch"] == k and len(meta["history"]) == k and meta["state"] == f"state-{k}.eqx"
    assert r.left == (["latest.json", f"state-{full.epochs}.eqx"],) * 2
    assert resumed.epochs == full.epochs and resumed.converged == full.converged
    np.testing.assert_array_equal(resumed.theta, full.theta)
    np.testing.assert_array_equal(resumed.states, full.states)
    np.testing.assert_array_equal(codes(resumed.status), codes(full.status))
    assert resumed.initial_J == full.initial_J
    for got, want in zip(resumed.history, full.history, strict=True):
        assert set(got) == set(want)
        for key in set(want) - TIMINGS:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)


@pytest.mark.parametrize("row, name", PAIRS)
def test_no_retrace_across_epochs(runs, row, name):
    """A ceemx function traced by epoch 1 is not traced again; one first needed later (a check
    run near convergence) is traced once; the resumed fit's epochs trace none."""
    r, ours = runs(row, name), ceemx_functions()
    first = set(r.traces[0])
    later = collections.Counter(f for epoch in r.traces[1:-1] for f in epoch if f in ours)
    again = {f: n for f, n in later.items() if f in first or n > 1}
    assert not again, again
    resumed = [f for epoch in r.resumed_traces[1:-1] for f in epoch if f in ours]
    assert not resumed, resumed
