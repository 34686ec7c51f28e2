"""``fit(..., noise="learn")``: rounds of certainty-equivalent fits and noise estimates.

A loop above the fit, not a mode of it: each round is one :func:`~.run.run_fit` at the current
noise, then :func:`~ceemx.identification.analysis.noise_estimate.estimate_noise` at the fitted θ.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from ceemx.data.checks import Prepared, promote_tree
from ceemx.identification.analysis.noise_estimate import (
    NoiseMoments,
    estimate_noise_prepared,
    start_states,
)
from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.fitting.run import run_fit
from ceemx.identification.noise_moments import NOISE_FIELDS
from ceemx.models.system import AbstractSystem

__all__ = ["NOISE_ROUND_RTOL", "learn_noise"]

#: the largest change of a learned noise factor (relative) under which the rounds stop
NOISE_ROUND_RTOL = 0.05


def learn_noise(
    system: AbstractSystem, inputs: Prepared, options: FitOptions, *, max_rounds: int = 6
) -> FitResult:
    """``fit(..., noise="learn")``: CE fits alternated with the noise the data show (module notes).

    The user's noise models give the shape (which components are noisier, correlations); one
    factor on each — process and observation — is learned, because those two factors are what a
    guess gets wrong by orders of magnitude and what moves a CE fit (J weighs dynamics against
    observations by them). Round 0 estimates the factors at the starting θ
    (:func:`~ceemx.identification.analysis.noise_estimate.estimate_noise`: the Laplace
    log-evidence maximised, a grid of decades around the
    guess first); a θ still far off then puts its model error into the process noise — a loose
    process noise, the safe side for the CE fit that follows. Each round fits θ and the states
    at the current noise (``fit`` with the given solver, warm-started), then re-estimates the
    factors at the fitted θ, again from the user's guess (so a degenerate maximum found once is
    not inherited); it stops when no factor changes by more than 5 % and the fit converged, or
    after ``max_rounds`` rounds. The result is the last round's fit, at noise consistent with
    its own residuals; ``FitResult.noise_rounds`` records each round.

    Args:
        system: the model at its initial θ, with the user's noise guess (as given).
        inputs: it, the data and the start states, prepared (:func:`ceemx.data.checks.prepare`).
        options: the other ``fit`` options (solver, trainable, max_epochs per round, ...).
        max_rounds: bound on the CE fits.

    Returns:
        The last round's :class:`ceemx.FitResult`, with ``noise_rounds`` filled in.
    """
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, int) or max_rounds < 1:
        raise ValueError(f"`max_rounds` must be an integer ≥ 1; got {max_rounds!r}.")
    guess, data = system, inputs.data
    system, nm, _ = estimate_noise_prepared(guess, data, start_states(inputs))
    states = nm.states
    rounds: list[dict] = [_round_record(0, system, nm, None)]
    result = None
    last: list = []
    for k in range(1, max_rounds + 1):
        with warnings.catch_warnings(record=True) as caught:  # the last round's are re-issued
            warnings.simplefilter("always")
            result = run_fit(system, Prepared(promote_tree(system, system), data, states), options)
        last = list(caught)
        fitted = _with_noise_of(result.system, guess)
        new, nm, _ = estimate_noise_prepared(fitted, data, result.states)
        change = float(np.max(np.abs(_stds(new, NOISE_FIELDS) / _stds(system, NOISE_FIELDS) - 1)))
        rounds.append(_round_record(k, new, nm, result, change))
        if not np.isfinite(change):
            break
        settled = change <= NOISE_ROUND_RTOL
        system, states = (result.system, result.states) if settled else (new, nm.states)
        if settled and result.converged:
            break
    assert result is not None
    for w in last:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return dataclasses.replace(result, noise_rounds=tuple(rounds))


def _with_noise_of(system: AbstractSystem, other: AbstractSystem) -> AbstractSystem:
    for field in NOISE_FIELDS:
        system = eqx.tree_at(
            lambda s, f=field: getattr(s, f), system, replace=getattr(other, field)
        )
    return system


def _round_record(k: int, system: AbstractSystem, nm: NoiseMoments, result, change=None) -> dict:
    return {
        "round": k,
        "process_noise_std": _stds(system, ("process_noise",)).round(12).tolist(),
        "obs_noise_std": _stds(system, ("obs_noise",)).round(12).tolist(),
        "log_evidence": nm.evidence,
        "epochs": None if result is None else result.epochs,
        "converged": None if result is None else bool(result.converged),
        "change": change,
    }


def _stds(system: AbstractSystem, fields: Sequence[str]) -> np.ndarray:
    out = []
    for field in fields:
        noise = getattr(system, field)
        out.append(np.sqrt(np.diagonal(np.asarray(noise.covariance(), float))))
    return np.concatenate(out) if out else np.zeros(0)
