"""Early stopping for :func:`ceemx.fit`: keep the model that simulates a held-out record best.

A flexible model (a hybrid's network, :mod:`ceemx.systems.hybrid`) keeps raising J on the record it
is fitted to after it stops generalising. :class:`EarlyStopping` is a :func:`ceemx.fit` callback
that scores every epoch's model by a validation free run (the protocol of
:func:`ceemx.benchmark_score`) on a record the fit does not see — cut from the *training* record,
never the test record — keeps the best model, stops after ``patience`` epochs without
improvement, and :meth:`EarlyStopping.restore` puts the best model into the fit's result.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.evaluation.initial_state import estimate_initial_state
from ceemx.evaluation.metrics import benchmark_score
from ceemx.infra.options import check_int, check_nonnegative
from ceemx.models.system import AbstractSystem

__all__ = ["EarlyStopping"]


def _score_options() -> frozenset[str]:
    """The keyword options of :func:`ceemx.benchmark_score`, read from the signatures.

    Its own and those it passes on to
    :func:`~ceemx.evaluation.initial_state.estimate_initial_state`.
    """
    own = inspect.signature(benchmark_score).parameters
    passed = inspect.signature(estimate_initial_state).parameters
    keyword = inspect.Parameter.KEYWORD_ONLY
    return frozenset(
        [k for k, v in own.items() if v.kind == keyword]
        + [k for k, v in passed.items() if v.kind == keyword and k != "return_status"]
    )


#: The options a validation score may set (``score_options``).
SCORE_OPTIONS = _score_options()


class EarlyStopping:
    """A :func:`ceemx.fit` callback: stop when a validation free-run stops improving; keep the best.

    Every epoch the current model is scored on ``validation`` by the benchmark protocol (initial
    state estimated from the first ``n_init`` outputs, free run over the rest, RMSE on
    y[n_init:] over all outputs; :func:`ceemx.benchmark_score`). The record must not be one the
    fit sees (cut it from the end of the training record) and never the test record. The epoch's
    score is recorded as ``"val_rmse"`` in the history.

    Args:
        validation: the validation record(s), as the model reads them.
        n_init: outputs used to estimate the initial state (≥ 1, < T).
        patience: epochs without a relative improvement of ``min_delta`` before stopping.
        min_delta: the relative improvement that resets the patience, counted from the score
            at the last reset (so a slow, steady improvement resets it once it adds up; any
            improvement is kept as the best model).
        every: score every ``every`` epochs (scoring costs one free run).
        start: the fit's starting model, scored as epoch 0 (recommended: :meth:`restore` then
            never returns a model worse on the validation record than the start, e.g. the
            physics model a hybrid starts from).
        score_options: keyword options of :func:`ceemx.benchmark_score` for the validation
            score (e.g. ``{"warm_process_noise": (1.0, None)}``: several initial-state starts).
        patience_from: ``"start"`` (default): the patience runs from the fit's first epoch;
            ``"improvement"``: from the first improvement of ``min_delta`` over the start (or,
            without ``start``, from the first finite score) — a term started at zero can sit at
            its start's score for many epochs while J climbs, then fall, and a fit that has
            not yet left its start has not stopped improving (the fit's ``max_epochs`` bounds
            the wait).

    After the fit, :attr:`best_system`, :attr:`best_epoch` and :attr:`best_rmse` hold the best
    model, :attr:`stopped` whether the patience ran out; :meth:`restore` returns the fit's result
    with it. A non-finite score (the model diverges on the validation record) never counts as
    the best.

    One instance watches one fit: passed to a second fit (its epochs start again), it starts
    over — the best model, the scores and the patience of the first fit are dropped (the
    ``start`` model and its score are kept) — so each round of ``fit(..., noise="learn")`` is
    watched on its own and :meth:`restore` reads the last. :meth:`restore` refuses a result
    whose history does not hold the validation scores of the fit it watched.
    """

    def __init__(
        self,
        validation: Trajectories,
        n_init: int,
        *,
        patience: int = 5,
        min_delta: float = 1e-3,
        every: int = 1,
        start: AbstractSystem | None = None,
        score_options: dict[str, Any] | None = None,
        patience_from: str = "start",
    ):
        """See the class docstring."""
        if not isinstance(validation, Trajectories):
            raise TypeError(
                f"`validation` must be ceemx.Trajectories; got {type(validation).__name__}."
            )
        T = validation.num_steps
        check_int("n_init", n_init, 1)
        if n_init >= T:
            raise ValueError(f"`n_init` must be an integer in [1, T = {T}); got {n_init!r}.")
        check_int("patience", patience, 1)
        check_int("every", every, 1)
        check_nonnegative("min_delta", min_delta)
        if min_delta >= 1:
            raise ValueError(f"`min_delta` must be a number in [0, 1); got {min_delta!r}.")
        if score_options is not None and not isinstance(score_options, dict):
            raise TypeError(
                f"`score_options` must be a dict or None; got {type(score_options).__name__}."
            )
        unknown = sorted(set(score_options or {}) - SCORE_OPTIONS)
        if unknown:
            raise ValueError(
                f"`score_options` has unknown keys {unknown}; allowed: {sorted(SCORE_OPTIONS)} "
                "(options of ceemx.benchmark_score)."
            )
        if patience_from not in ("start", "improvement"):
            raise ValueError(
                f"`patience_from` must be 'start' or 'improvement'; got {patience_from!r}."
            )
        if start is not None and not isinstance(start, AbstractSystem):
            raise TypeError(f"`start` must be a ceemx.AbstractSystem; got {type(start).__name__}.")
        self.validation = validation
        self.n_init = n_init
        self.score_options = dict(score_options or {})
        self.patience = patience
        self.min_delta = float(min_delta)
        self.every = every
        self.patience_from = patience_from
        self._start: tuple[AbstractSystem, float] | None = None
        if start is not None:
            self._start = (start, self.score(start))
        self._start_over()

    def _start_over(self) -> None:
        """The state before a fit: no epoch watched, the start model the best (when finite)."""
        self.best_system: AbstractSystem | None = None
        self.best_epoch = 0
        self._progress_epoch = 0
        self._progress_rmse = math.inf  # the score at the last patience reset
        self._improved_at: int | None = None  # the first reset's epoch (None: none yet)
        self.best_rmse = math.inf
        self.scores: list[tuple[int, float]] = []
        self._last_epoch = 0  # the last epoch of the fit being watched (0: none yet)
        self.stopped = False  # whether the patience ran out (this instance stopped the fit)
        if self._start is not None:
            start, rmse = self._start
            self.scores.append((0, rmse))
            if np.isfinite(rmse):
                self.best_system, self.best_rmse = start, rmse
                self._progress_rmse = rmse

    def errors(self, system: AbstractSystem) -> tuple[np.ndarray, np.ndarray]:
        """``system``'s validation free-run errors, ``(errors, observed)``, each (B, T − n_init, m).

        The free run of :func:`ceemx.benchmark_score` (its ``scale`` applied: the errors are
        in the score's units); ``observed`` is the mask of the scored entries (an unobserved
        entry's error is 0). :meth:`score` is their RMSE; :func:`ceemx.evaluation.
        paired_bootstrap.clearly_better` compares two models' errors sample by sample.
        """
        s = benchmark_score(system, self.validation, self.n_init, **self.score_options)
        scale = self.score_options.get("scale")
        scale = 1.0 if scale is None else np.asarray(scale, np.float64)
        y = np.asarray(self.validation.y, np.float64)[:, self.n_init :]
        observed = np.asarray(self.validation.mask, bool)[:, self.n_init :]
        y_sim = np.asarray(s.y_sim, np.float64)[:, self.n_init :]
        with np.errstate(invalid="ignore", over="ignore"):  # a diverged run: its errors inf/NaN
            return np.where(observed, scale * (y_sim - y), 0.0), observed

    def score(self, system: AbstractSystem) -> float:
        """The validation free-run RMSE of ``system``: over every output, each weighted alike.

        The root of the mean over trajectories and outputs of each one's mean squared
        :meth:`errors` over its observed entries.
        """
        errors, observed = self.errors(system)
        count = np.maximum(observed.sum(axis=1), 1)
        with np.errstate(invalid="ignore", over="ignore"):
            return float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1) / count)))

    def __call__(self, info) -> dict | bool:
        """Score the epoch's model; ``False`` stops the fit."""
        if info.epoch <= self._last_epoch:  # epochs start again: another fit (class notes)
            self._start_over()
        self._last_epoch = info.epoch
        if info.epoch % self.every:
            return {}
        rmse = self.score(info.system)
        self.scores.append((info.epoch, rmse))
        if np.isfinite(rmse) and rmse < self.best_rmse:
            if rmse < self._progress_rmse * (1 - self.min_delta):
                # patience counts from a real improvement: min_delta below the score at the last
                # reset, so many small steps count once they add up
                self._progress_epoch, self._progress_rmse = info.epoch, rmse
                if self._improved_at is None:
                    self._improved_at = info.epoch
            self.best_system, self.best_epoch, self.best_rmse = info.system, info.epoch, rmse
        info.record["val_rmse"] = rmse
        waiting = self.patience_from == "improvement" and self._improved_at is None
        if not waiting and info.epoch - self._progress_epoch >= self.patience * self.every:
            self.stopped = True
            return False
        return {}

    def restore(self, result):
        """``result`` with the best validation model as its system (states are kept).

        Raises:
            ValueError: no epoch was watched (the instance was not among the fit's
                ``callbacks``), or ``result`` is not the fit this instance watched last: its
                history does not hold the validation scores recorded in that fit.
        """
        watched = [(epoch, rmse) for epoch, rmse in self.scores if epoch > 0]
        if not self._last_epoch:
            raise ValueError(
                "this EarlyStopping has watched no epoch of a fit: pass it to the fit "
                "(fit(..., callbacks=[early_stopping])) before restoring its result."
            )
        recorded = {
            (h.get("epoch"), _key(h["val_rmse"])) for h in result.history if "val_rmse" in h
        }
        if not all((epoch, _key(rmse)) in recorded for epoch, rmse in watched):
            raise ValueError(
                "`result` is not the fit this EarlyStopping watched: its history does not hold "
                f"the validation scores recorded at epochs {[e for e, _ in watched]}. Restore the "
                "result of the fit it was passed to (its last one: one instance watches one fit "
                "at a time)."
            )
        if self.best_system is None:
            return result
        theta = result.theta
        if result.problem is not None:
            theta = result.problem.theta_of(self.best_system)
        return dataclasses.replace(result, system=self.best_system, theta=theta)


def _key(rmse: float) -> float | str:
    """A validation score as a set member (NaN, which equals nothing, as a string)."""
    value = float(rmse)
    return "nan" if math.isnan(value) else value
