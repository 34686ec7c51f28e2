"""The epoch loop of a fit: step, record, stopping rule, callbacks, progress bar, checkpoints."""

from __future__ import annotations

import dataclasses
import sys
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

__all__ = ["run_epochs"]


def run_epochs(start: FitStart, options: FitOptions) -> tuple[FitState, bool]:
    """The epochs from ``start``: (the last state, whether the solver converged).

    They run until the solver converges or stops, a callback stops them, or ``max_epochs``
    (resumed ones included) have run. Each epoch's record is appended to ``start.history``.
    Over several processes only process 0 shows progress and writes checkpoints.
    """
    solver, problem, state, history = start.solver, start.problem, start.state, start.history
    show = (sys.stderr.isatty() if options.progress is None else options.progress) and (
        is_main_process()
    )
    bar = _Progress(show, options.max_epochs, len(history), type(solver).__name__)
    converged = bool(history and history[-1].get("converged", False))
    stopped = bool(history and history[-1].get("stop", False))
    term = TermProgress.of(problem.build(state.theta), total_J(state))  # None: no learned term
    try:
        while len(history) < options.max_epochs and not (converged or stopped):
            epoch = len(history) + 1
            t0 = time.perf_counter()
            before = state
            state, own = solver.step(problem, state)
            if epoch == 1 and all_failed(state) and not all_failed(before):
                # why every trajectory failed at once, when the start says (else the status does)
                refuse_failed_start(problem, before.theta, before.states, solver, at_init=False)
            record = _record(epoch, before, state, time.perf_counter() - t0, own)
            stop, converged = solver.terminate(problem, before, state, record)
            info = EpochInfo(epoch, problem.build(state.theta), state.states, record)
            if term is not None:
                stop, converged = _term_rule(term, solver, problem, state, info, stop, converged)
            stopped = _run_callbacks(options.callbacks, info) or stop
            record["converged"] = converged
            record["stop"] = converged or stopped
            history.append(record)
            bar.update(record)
            if options.checkpoint is not None:
                _save(options, state, history, start.fingerprint)
    finally:
        bar.close()
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


def _record(epoch: int, before: FitState, after: FitState, elapsed: float, own: dict) -> dict:
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


class _Progress:
    def __init__(self, enabled: bool, total: int, initial: int, desc: str):
        self.bar = None
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=initial, desc=desc, unit="epoch", leave=True)

    def update(self, record):
        if self.bar is not None:
            self.bar.set_postfix(J=f"{record['J']:.6g}", t=f"{record['time']:.2f}s")
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()
