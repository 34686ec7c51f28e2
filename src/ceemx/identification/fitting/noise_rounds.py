"""``fit(..., noise="learn")``: rounds of certainty-equivalent fits and noise estimates.

A loop above the fit, not a mode of it: each round is one :func:`~.run.run_fit` at the current
noise, then :func:`~ceemx.identification.analysis.noise_estimate.estimate_noise` at the fitted θ.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from ceemx.data.checks import Prepared, promote_tree
from ceemx.identification.analysis.noise_estimate import (
    NoiseEstimateWarning,
    NoiseMoments,
    estimate_noise_prepared,
    start_states,
)
from ceemx.identification.analysis.noise_floor import check_informative
from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.fitting.run import run_fit
from ceemx.identification.noise_moments import NOISE_FIELDS
from ceemx.infra.warn import warn
from ceemx.models.system import AbstractSystem

__all__ = ["MAX_NOISE_ROUNDS", "NOISE_ROUND_RTOL", "learn_noise"]

#: the largest change of a learned noise factor (relative) under which the rounds stop
NOISE_ROUND_RTOL = 0.05

#: the rounds' bound. A record without process noise needs seven: each round's fit at a smaller
#: σ_w makes θ fit the deterministic model better, and the next estimate falls a decade or more,
#: until the evidence is flat in σ_w (the README's coupled Lorenz: 0.38, 0.024, 1e-3, 2.4e-4,
#: 2.4e-5, 2.4e-7, then settled)
MAX_NOISE_ROUNDS = 10


def learn_noise(
    system: AbstractSystem,
    inputs: Prepared,
    options: FitOptions,
    *,
    max_rounds: int = MAX_NOISE_ROUNDS,
) -> FitResult:
    """``fit(..., noise="learn")``: CE fits alternated with the noise the data show (module notes).

    The user's noise models give the shape; one factor on each — process and observation — is
    learned: what a guess gets wrong by orders of magnitude. Round 0 estimates them at the start
    (:func:`~ceemx.identification.analysis.noise_estimate.estimate_noise`: the Laplace
    log-evidence maximised, a grid of decades around the guess first, the observation noise
    held at or above its floors from the data, :mod:`~ceemx.identification.analysis.noise_floor`).
    Each round fits θ and the states at the current noise (``fit`` with the given solver,
    warm-started), then re-estimates the factors at the fitted θ, again from the user's guess
    (its search box and floors, so a degenerate maximum found once is not inherited); its grid
    spans one decade either way of the previous estimate where that was not degenerate, and each
    factor alone over the guess's decades (the full grid of decades each round cost most of the
    rounds' posterior evaluations), else three decades of the guess. It stops when no factor
    changes by more than 5 % and the fit converged. After ``max_rounds`` rounds without that, it
    warns and the result is not converged.

    A degenerate observation noise (``NoiseMoments.degenerate``: the data do not determine σ_v,
    which is held at the upper end of its evidence margin) is fitted at only when made after a
    converged fit. Before that, at a θ still far off, the process noise absorbs the model error,
    and a CE fit at that noise leaves the hidden states free and hardly moves θ: the rounds
    creep (a Bouc–Wen record: six rounds, σ_v 30× the truth, free run 4.6e-5 m against
    5e-9 m). The round fits at the previous noise instead — the first at the user's, from the MAP
    states of the estimate — and the next estimate is made at a fitted θ. Made after a converged
    fit, a degenerate estimate is the data's answer (a process noise that dominates the
    observation noise: the record cannot reject σ_v → 0 even at the truth); kept out there, a
    guess 100× too tight stayed the fit's noise with intervals 100× too narrow. An estimate held
    at the search box's upper edge (the evidence flat over the whole box) is never fitted at.
    When no estimate is usable the fit stays at the user's noise, with a warning that the noise
    was not learned.

    The result is the last round's fit, at the noise that round used — the last record of
    ``FitResult.noise_rounds``: round 0 the estimate at the start; round k the noise fit k ran
    at, its epochs and whether it converged, and of the estimate made after it the evidence,
    ``floored``, ``degenerate``, ``notes`` and ``change`` (how far it moved the factors; 0 when
    kept out), ``settled``, ``time`` (seconds of the round); the last also ``learned``.

    Args:
        system: the model at its initial θ, with the user's noise guess (as given).
        inputs: it, the data and the start states, prepared (:func:`ceemx.data.checks.prepare`).
        options: the other ``fit`` options (solver, trainable, max_epochs per round, ...).
        max_rounds: bound on the CE fits.

    Returns:
        The last round's :class:`ceemx.FitResult`, with ``noise_rounds`` filled in.

    Raises:
        ValueError: for data with no observation, or whose observed outputs are all constant.
    """
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, int) or max_rounds < 1:
        raise ValueError(f"`max_rounds` must be an integer ≥ 1; got {max_rounds!r}.")
    guess, data = system, inputs.data
    check_informative(data)
    clock = time.perf_counter()
    estimate, nm, _ = estimate_noise_prepared(guess, data, start_states(inputs))
    rounds: list[dict] = [_round_record(0, estimate, nm, None, time.perf_counter() - clock)]
    system, states, learned = _next_noise(guess, estimate, nm)
    around = None if nm.degenerate else estimate  # the grid's centre (estimate_noise_prepared)
    result, settled, last = None, False, []
    for k in range(1, max_rounds + 1):
        clock, opts = time.perf_counter(), _round_options(options, k)  # its progress: round k
        with warnings.catch_warnings(record=True) as caught:  # the last round's are re-issued
            warnings.simplefilter("always")
            result = run_fit(system, Prepared(promote_tree(system, system), data, states), opts)
        last = list(caught)
        fitted = _with_noise_of(result.system, guess)
        new, new_nm, _ = estimate_noise_prepared(fitted, data, result.states, around=around)
        usable = _usable(new_nm, bool(result.converged))
        change = _change(new, system) if usable else 0.0  # an unusable one is kept out
        learned = learned or usable
        around = None if new_nm.degenerate else new
        settled = bool(change <= NOISE_ROUND_RTOL)
        rounds.append(_round_record(k, system, new_nm, result, time.perf_counter() - clock))
        rounds[-1].update(
            change=change, settled=settled and bool(result.converged), noise_settled=settled
        )
        if (settled and result.converged) or not np.isfinite(change):
            break
        if not settled:  # the next round fits at the new estimate, from its MAP states
            system, states = new, new_nm.states
        else:  # the same noise: the fit goes on from where it stopped
            system, states = result.system, result.states
    assert result is not None
    for w in last:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    rounds[-1]["learned"] = learned
    if not learned:
        warn(_not_learned(rounds), NoiseEstimateWarning)
    if not (settled and result.converged):
        warn(_unsettled(rounds, result.converged), NoiseEstimateWarning)
        result = dataclasses.replace(result, converged=False)
    return dataclasses.replace(result, noise_rounds=tuple(rounds))


def _round_options(options: FitOptions, k: int) -> FitOptions:
    """``options`` with the progress display's label naming round ``k``."""
    label = ", ".join(s for s in (options.progress_label, f"noise round {k}") if s)
    return dataclasses.replace(options, progress_label=label)


def _next_noise(guess: AbstractSystem, estimate: AbstractSystem, nm: NoiseMoments):
    """``(system, states, learned)`` the first fit starts from.

    The start's estimate, or the guess where that estimate is degenerate (analysis.noise_floor:
    at a θ still far off, the model error the process noise absorbs leaves σ_v → 0, and a CE fit
    at that noise hardly moves θ — the states interpolate the data).
    """
    if not _usable(nm, fitted=False):
        return guess, nm.states, False
    return estimate, nm.states, True


def _usable(nm: NoiseMoments, fitted: bool) -> bool:
    """Whether a fit may run at the estimate (module notes of :func:`learn_noise`).

    Any estimate that is not degenerate. A degenerate one only when made after a converged fit
    (``fitted``), where it is the data's answer and not a θ still far off, and held at the upper
    end of its evidence margin, the loose side of what the data allow — not at the search box's
    upper edge (the evidence flat over the whole box says nothing of the data).
    """
    if not nm.degenerate:
        return True
    return fitted and not set(nm.degenerate) & set(nm.at_edge)


def _change(new: AbstractSystem, old: AbstractSystem) -> float:
    """The largest relative change of a noise std from ``old`` to ``new``."""
    return float(np.max(np.abs(_stds(new, NOISE_FIELDS) / _stds(old, NOISE_FIELDS) - 1)))


def _not_learned(rounds: list[dict]) -> str:
    return (
        "fit(..., noise='learn') could not learn the noise from this record: at every fitted θ "
        "the evidence was flat over the observation noise's whole search box (seven decades "
        "either way of the guess; FitResult.noise_rounds: 'notes'), so the data do not "
        "determine it and the fit is at the noise given. Give the sensor's accuracy as the "
        "observation noise and fit with noise='fixed', or learn the noise with "
        "solver=ceemx.LaplaceEM()."
    )


def _unsettled(rounds: list[dict], converged: bool) -> str:
    last, n = rounds[-1], len(rounds) - 1
    if last["change"] <= NOISE_ROUND_RTOL:
        head = f"stopped after {n} rounds unsettled: the noise held, but the last round's fit"
        why = " did not converge"
    else:
        head = f"stopped after {n} rounds before the noise settled"
        why = (
            f": the last estimate moved a noise factor by {100 * last['change']:.3g} % (more "
            f"than {100 * NOISE_ROUND_RTOL:.3g} %)"
            + ("" if converged else ", and its fit did not converge")
        )
    return (
        f"fit(..., noise='learn') {head}{why}. The result is "
        "the last round's fit at the noise it used, reported not converged "
        "(FitResult.noise_rounds holds every round). Fit again from it (more max_epochs), or "
        "at a fixed noise."
    )


def _with_noise_of(system: AbstractSystem, other: AbstractSystem) -> AbstractSystem:
    for field in NOISE_FIELDS:
        system = eqx.tree_at(
            lambda s, f=field: getattr(s, f), system, replace=getattr(other, field)
        )
    return system


def _round_record(k: int, system: AbstractSystem, nm: NoiseMoments, result, seconds) -> dict:
    """The record of round k.

    The noise its fit ran at (round 0: the start's estimate), the flags of the estimate made
    after it (round 0: its own), its fit's epochs, the round's seconds.
    """
    return {
        "round": k,
        "process_noise_std": _stds(system, ("process_noise",)).round(12).tolist(),
        "obs_noise_std": _stds(system, ("obs_noise",)).round(12).tolist(),
        "log_evidence": nm.evidence,
        "floored": nm.floored,
        "degenerate": nm.degenerate,
        "notes": nm.notes,
        "epochs": None if result is None else result.epochs,
        "converged": None if result is None else bool(result.converged),
        "change": None,
        "time": seconds,
    }


def _stds(system: AbstractSystem, fields: Sequence[str]) -> np.ndarray:
    out = []
    for field in fields:
        noise = getattr(system, field)
        out.append(np.sqrt(np.diagonal(np.asarray(noise.covariance(), float))))
    return np.concatenate(out) if out else np.zeros(0)
