"""One fit at the system's noise: start, run the epochs, finish."""

from __future__ import annotations

import contextlib
import time

from ceemx.data.checks import Prepared
from ceemx.identification.fitting.epochs import epoch_record, fit_progress, outcome, run_epochs
from ceemx.identification.fitting.finish import finish_fit
from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.identification.fitting.result import FitResult
from ceemx.identification.fitting.start import FitStart, start_fit
from ceemx.identification.solvers.base import FitState
from ceemx.models.system import AbstractSystem

__all__ = ["run_fit"]


def run_fit(system: AbstractSystem, inputs: Prepared, options: FitOptions) -> FitResult:
    """:func:`ceemx.fit` with ``noise="fixed"`` of prepared inputs and checked options.

    ``system`` is the model as given (its problem is built from it); ``inputs`` hold it, the data
    and the start states prepared (:func:`ceemx.data.checks.prepare`).
    """
    name = type(options.solver).__name__
    name += f" ({options.progress_label})" if options.progress_label else ""
    with contextlib.ExitStack() as hold:  # the checkpoint folder's lock, for the whole fit
        bar = hold.enter_context(fit_progress(options, name))
        bar.status("start states, compiling")
        start = start_fit(system, inputs, options, hold)
        if start.compiling is not None:  # the epoch programs compiled beside the start states
            start.compiling.join()
        state, converged = run_epochs(start, options, bar)
        if start.history and not options.spread:  # the arrays of one host
            state, converged = end_check(start, state, converged)
        bar.status("uncertainty and checks")
        result = finish_fit(start, state, converged, options)
        bar.close(outcome(start.history, options.max_epochs))
        return result


def end_check(start: FitStart, state: FitState, converged: bool) -> tuple[FitState, bool]:
    """(state, converged) after the solver's check of the end point (``end_check``).

    Its record joins the history as one more epoch; ``converged`` is the check's verdict where
    it made one, the epochs' otherwise.
    """
    t0 = time.perf_counter()
    new, verdict, own = start.solver.end_check(start.problem, state)
    if not own:
        return state, converged
    converged = converged if verdict is None else verdict
    record = epoch_record(len(start.history) + 1, state, new, time.perf_counter() - t0, own)
    record["converged"] = converged
    record["stop"] = True
    start.history.append(record)
    return new, converged
