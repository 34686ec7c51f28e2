"""The end of a fit: the solver's last word, the excluded trajectories, the noise check.

``converged`` is the solver's stopping rule *and* what the end point shows (:func:`end_status`):
never true when no trajectory took part, when J is not finite (status ``nonfinite_objective``),
when θ or the states never moved in any epoch (status ``never_moved``: the rule was met without
a fit — a start where the model does not depend on what is learned, steps that all led where
the model is not finite, options that freeze the iterates), or when a trajectory taking part
ends ``stalled`` (its solver found no step that decreases the objective before its tolerances
were met: the end point is not a certified optimum).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ceemx.data.arrays import back_like, on_host
from ceemx.identification.analysis.noise_check import NoiseCheckWarning, noise_check
from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.fitting.start import FitStart, gathered
from ceemx.identification.noise_moments import NOISE_FIELDS
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import FitState, total_J
from ceemx.infra.distributed import to_host
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
    took_part = bool(np.any(np.asarray(state.weights) > 0))
    state, converged = end_status(state, start.state, history, converged)
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


def end_status(
    state: FitState, first: FitState, history: list, converged: bool
) -> tuple[FitState, bool]:
    """(state with its statuses, converged) as the end point and the epochs show them.

    See the module notes: the statuses of the trajectories taking part become
    ``nonfinite_objective`` where their J is not finite, ``never_moved`` (the ``successful``
    ones) when θ — or the states — did not change in any epoch; ``converged`` is false then,
    when no trajectory took part, and when one taking part ended ``stalled``. A trajectory that
    took part in ``first`` (the state the epochs started from) with a finite J and failed later
    (``nonfinite``: the solver's words for the start of its own solve) reads
    ``nonfinite_objective`` too.
    """
    ok = np.asarray(to_host(state.weights) > 0).reshape(-1)
    status = state.status
    if history:  # failed during the epochs: the end point is not finite, not the start
        nonfinite = int(codes(RESULTS.nonfinite))
        late = np.asarray(codes(status)).reshape(-1) == nonfinite
        late &= np.asarray(to_host(first.weights) > 0).reshape(-1)
        late &= np.asarray(codes(first.status)).reshape(-1) != nonfinite
        late &= np.isfinite(np.asarray(to_host(first.J))).reshape(-1)
        status = select(as_jax(late), RESULTS.nonfinite_objective, status)
    if not ok.any():
        return dataclasses.replace(state, status=status), False
    J_b = np.asarray(to_host(state.J)).reshape(-1)
    bad_J = ok & ~np.isfinite(J_b)
    if bad_J.any():
        status = select(as_jax(bad_J), RESULTS.nonfinite_objective, status)
        converged = False
    if history and _never_moved(state, history):
        good = ok & (np.asarray(codes(status)).reshape(-1) == int(codes(RESULTS.successful)))
        status = select(as_jax(good), RESULTS.never_moved, status)
        converged = False
    stalled = np.asarray(codes(status)).reshape(-1) == int(codes(RESULTS.stalled))
    if (ok & stalled).any() or not np.isfinite(total_J(state)):
        converged = False
    return dataclasses.replace(state, status=status), bool(converged)


def _never_moved(state: FitState, history: list) -> bool:
    """Whether θ stayed exactly where it started, or the states did while θ moved materially.

    States that never change while θ moves by more than √ε·max(1, ‖θ‖) are an E-step that
    refused every step (every trial led where the model is not finite): θ was fitted to states
    the method could not move. States unchanged while θ too stays within rounding of the start
    are a fit started at its optimum (its stopping rule is met at once, legitimately).
    """
    steps = np.asarray([h["dtheta_norm"] for h in history], np.float64)
    theta_size = np.size(state.theta)
    # an epoch whose move was discarded for lowering the evidence (Laplace EM's
    # ``evidence_fell``) moved: its θ stays because the start was the better point
    moved = any(h.get("evidence_fell") for h in history)
    if theta_size > 0 and np.all(steps == 0.0) and not moved:
        return True
    if not all(h["dx_norm"] == 0.0 for h in history):
        return False
    theta = np.asarray(to_host(state.theta))
    eps = float(np.finfo(theta.dtype).eps)
    material = np.sqrt(eps) * max(1.0, float(np.linalg.norm(theta.astype(np.float64))))
    return bool(np.sum(steps) > material)


def _with_excluded(state: FitState, all_states, excluded: np.ndarray):
    """States and statuses of every trajectory: the excluded ones as given, status ``outlier``."""
    if not excluded.any():
        return state.states, state.status
    keep = np.flatnonzero(~excluded)
    if on_host((all_states, state.states)):  # NumPy on the host: no program per shape
        out = np.array(all_states)
        out[keep] = np.asarray(state.states)
        out_states = back_like(out, all_states)
    else:
        out_states = all_states.at[as_jax(keep)].set(state.states)
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
