"""The end of a fit: the solver's last word, the excluded trajectories, the noise check."""

from __future__ import annotations

import dataclasses

import numpy as np

from ceemx.identification.analysis.noise_check import NoiseCheckWarning, noise_check
from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.fitting.start import FitStart, gathered
from ceemx.identification.noise_moments import NOISE_FIELDS
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import FitState, total_J
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, codes, from_codes, select
from ceemx.lib.tree import as_jax

__all__ = ["finish_fit"]


def finish_fit(start: FitStart, state: FitState, converged: bool, options: FitOptions) -> FitResult:
    """The :class:`FitResult` of the epochs run from ``start`` to ``state``.

    The solver's ``postprocess`` and ``identifiability``; the excluded trajectories' states put
    back as given (status ``outlier``); the end-of-fit noise check (``options.diagnose``). A
    multi-process fit's arrays are gathered first: every process gets the whole result.
    """
    solver, problem, all_states, history = (
        start.solver,
        start.problem,
        start.all_states,
        start.history,
    )
    if options.spread:  # the rest runs on every process alike, on gathered arrays (the result)
        state, all_states = gathered(dataclasses.replace(state, cache=None)), gathered(all_states)
        problem = problem.with_data(gathered(problem.data))
    state = solver.postprocess(problem, state)
    # Never "converged" when no trajectory took part or J is not finite.
    took_part = bool(np.any(np.asarray(state.weights) > 0))
    converged = bool(converged and took_part and np.isfinite(total_J(state)))
    found = solver.identifiability(problem, state, history, converged) if took_part else None
    out_states, status = _with_excluded(state, all_states, start.excluded)
    check = _check_noise(problem, state, converged) if options.diagnose and history else None
    health = start.health
    return FitResult(
        problem.build(state.theta),
        out_states,
        status,
        history,
        converged,
        solver,
        start.initial_J,
        tuple(int(b) for b in np.flatnonzero(start.excluded)),
        None if health is None else tuple(float(r) for r in health.mean_square),
        problem=problem,
        theta=state.theta,
        weights=state.weights,
        identifiability=found,
        noise_check=check,
    )


def _with_excluded(state: FitState, all_states, excluded: np.ndarray):
    """States and statuses of every trajectory: the excluded ones as given, status ``outlier``."""
    if not excluded.any():
        return state.states, state.status
    keep = as_jax(np.flatnonzero(~excluded))
    out_states = all_states.at[keep].set(state.states)
    codes_all = np.full(excluded.shape, -1)
    codes_all[~excluded] = np.asarray(codes(state.status)).reshape(-1)
    status = select(as_jax(excluded), RESULTS.outlier, from_codes(np.maximum(codes_all, 0)))
    return out_states, status


def _check_noise(problem: FitProblem, state: FitState, converged: bool):
    """The end-of-fit noise check (``analysis.noise_check``); warns on failure."""
    learned = tuple(f for f in NOISE_FIELDS if problem.trains(f))
    check = noise_check(
        problem.build(state.theta),
        problem.data,
        state.states,
        weights=state.weights,
        n_params=int(np.size(state.theta)),
        learned=learned,
        converged=converged,
    )
    if check is not None and check.message:
        warn(check.message, NoiseCheckWarning)
    return check
