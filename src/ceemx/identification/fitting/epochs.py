"""The epoch loop of a fit: step, record, stopping rule, callbacks, progress bar, checkpoints."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.result import EpochInfo
from ceemx.identification.fitting.start import (
    FitStart,
    all_failed,
    gathered,
    refuse_failed_start,
)
from ceemx.identification.fitting.term_progress import TermProgress
from ceemx.identification.solvers.base import FitState, objective_scale, total_J
from ceemx.infra import checkpoint as ckpt
from ceemx.infra.distributed import is_main_process, to_host
from ceemx.infra.progress import Progress

__all__ = ["epoch_record", "fit_progress", "outcome", "run_epochs"]


def fit_progress(options: FitOptions, name: str) -> Progress:
    """The progress display of one fit (:mod:`ceemx.infra.progress`; process 0 only)."""
    show = options.progress if is_main_process() else False
    return Progress(name, options.max_epochs, show=show, unit="epoch")


def outcome(history: list, max_epochs: int) -> str:
    """How the epochs ended, for the progress display: ``"converged at 8/50 epochs"``."""
    n = len(history)
    last = history[-1] if history else {}
    if last.get("converged", False):
        return f"converged at {n}/{max_epochs} epochs"
    if last.get("stop", False):
        return f"stopped at {n}/{max_epochs} epochs"
    return f"not converged after {n}/{max_epochs} epochs"


def run_epochs(
    start: FitStart, options: FitOptions, bar: Progress | None = None
) -> tuple[FitState, bool]:
    """The epochs from ``start``: (the last state, whether the solver converged).

    They run until the solver converges or stops, a callback stops them, or ``max_epochs``
    (resumed ones included) have run. Each epoch's record is appended to ``start.history``.
    Over several processes only process 0 shows progress and writes checkpoints. ``bar``: the
    fit's display (:func:`fit_progress`; ``None``: none), updated after every epoch.
    """
    solver, problem, state, history = start.solver, start.problem, start.state, start.history
    bar = Progress("", show=False) if bar is None else bar
    converged = bool(history and history[-1].get("converged", False))
    stopped = bool(history and history[-1].get("stop", False))
    term = TermProgress.of(problem.build(state.theta), total_J(state))  # None: no learned term
    if history:  # a resumed fit
        bar.update(len(history))
    while len(history) < options.max_epochs and not (converged or stopped):
        epoch = len(history) + 1
        if epoch == 1:
            bar.status("first epoch")
        t0 = time.perf_counter()
        before = state
        state, own = solver.step(problem, state)
        if epoch == 1 and all_failed(state) and not all_failed(before):
            # why every trajectory failed at once, when the start says (else the status does)
            refuse_failed_start(problem, before.theta, before.states, solver, at_init=False)
        record = epoch_record(epoch, before, state, time.perf_counter() - t0, own)
        stop, converged = solver.terminate(problem, before, state, record)
        info = EpochInfo(epoch, problem.build(state.theta), state.states, record)
        if term is not None:
            stop, converged = _term_rule(term, solver, problem, state, info, stop, converged)
        stopped = _run_callbacks(options.callbacks, info) or stop
        record["converged"] = converged
        record["stop"] = converged or stopped
        history.append(record)
        bar.update(1, f"J={record['J']:.6g}, {record['time']:.2f} s")
        if options.checkpoint is not None:
            _save(options, state, history, start.fingerprint)
    return state, converged


def _term_rule(term, solver, problem, state, info, stop, converged) -> tuple[bool, bool]:
    """(stop, converged) of a model with a learned term (:mod:`.term_progress`).

    Converged only once the term settled over the window; a solver that stopped because it
    converged goes on until then. ``term_settled`` in the record says which.
    """
    tolerance = float(solver.rtol) * objective_scale(problem, state) + float(solver.atol)
    settled = term.update(info.system, float(info.record["J"]), tolerance)
    info.record["term_settled"] = settled
    if converged and not settled:
        return False, False
    return stop, converged and settled


def _save(options: FitOptions, state: FitState, history: list, fingerprint) -> None:
    """The epoch's checkpoint (gathered first over several processes: a collective)."""
    saved = dataclasses.replace(state, cache=None)
    saved = gathered(saved) if options.spread else saved  # every process takes part
    if options.checkpoint is not None and (not options.spread or is_main_process()):
        ckpt.save(options.checkpoint, saved, history, fingerprint)


def epoch_record(epoch: int, before: FitState, after: FitState, elapsed: float, own: dict) -> dict:
    """The driver's history keys (see :class:`ceemx.FitResult`) and the solver's own."""
    ok = to_host(after.weights) > 0
    dx = np.where(ok[:, None, None], to_host(after.states) - to_host(before.states), 0.0)
    return {
        "epoch": epoch,
        "J_before": total_J(before),
        "J": total_J(after),
        "J_per_trajectory": to_host(after.J).tolist(),
        "dtheta_norm": float(np.linalg.norm(to_host(after.theta) - to_host(before.theta))),
        "dx_norm": float(np.linalg.norm(dx)),
        "failed_trajectories": np.flatnonzero(~ok).tolist(),
        "time": elapsed,
        **own,
    }


def _run_callbacks(callbacks: Sequence[Callable[[EpochInfo], Any]], info: EpochInfo) -> bool:
    """Call each callback, merging returned dicts into the record; whether one returned False."""
    stop = False
    for cb in callbacks:
        out = cb(info)
        if isinstance(out, dict):
            info.record.update(out)
        elif out is False:
            stop = True
    return stop
