"""Progress of long work: a bar in a terminal or a notebook, one-line logs anywhere else.

:class:`Progress` is the one display behind the fits' epoch bar and the long evaluations
(:func:`ceemx.benchmark_score`, :meth:`ceemx.FitResult.diagnostics`). What it shows depends on
where stderr goes and on ``show`` (a fit's ``progress=``):

- stderr a terminal, or a Jupyter notebook: a ``tqdm.auto`` bar (a widget in a notebook); a
  fit's bar at once, other work's once it has run :data:`DELAY` seconds.
- stderr a file, a pipe, a CI log: one-line logs; with ``show=None`` (default) only for work
  that runs past :data:`DELAY` seconds, with ``show=True`` always (at least the last line).
- ``show=False``: nothing.

One-line logs are written every :data:`EVERY` seconds while the work runs, and a last line with
its outcome (``ceemx: JointLM: converged at 8/50 epochs (3.1 s)``); a bar ends on that outcome
too. A heartbeat thread writes them (and refreshes a bar's clock), so a step that runs long —
the first epoch, which compiles — is reported while it runs, not after.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any, Literal, TextIO

__all__ = ["DELAY", "EVERY", "FIRST", "Progress", "interactive", "task"]

#: seconds of work before a log line appears when nobody asked for progress (``show=None``)
DELAY = 5.0
#: seconds between two log lines of the same work (and before the first one with ``show=True``)
EVERY = 30.0
#: seconds before the first log line when progress was asked for (``show=True``)
FIRST = 2.0
#: seconds between two heartbeats (a bar's clock, a due log line)
_TICK = 0.5


def _in_notebook() -> bool:
    """Whether this process is a Jupyter kernel (where stderr is no terminal, yet a bar shows)."""
    ipython = sys.modules.get("IPython")
    if ipython is None:
        return False
    try:
        shell = ipython.get_ipython()
    except AttributeError:  # a partial IPython installation
        return False
    return shell is not None and type(shell).__name__ == "ZMQInteractiveShell"


def interactive(stream: Any) -> bool:
    """Whether ``stream`` shows a live bar: a terminal, or stderr in a Jupyter notebook."""
    try:
        if stream.isatty():
            return True
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
    return (stream is sys.stderr or stream is sys.__stderr__) and _in_notebook()


Mode = Literal["off", "bar", "log"]


def _elapsed(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


class Progress:
    """A bar, or one-line logs, for one piece of work (see the module notes).

    Args:
        desc: what runs, e.g. ``"JointLM"`` or ``"benchmark_score: free run of 2 records"``.
        total: the number of steps (``None``: work without steps).
        initial: steps already done (a resumed fit).
        unit: the steps' name (``"epoch"``).
        show: ``None`` (default): a bar where it can show, else logs for work longer than
            :data:`DELAY`; ``True``: a bar or logs from the start; ``False``: nothing.
        stream: where to write (default ``sys.stderr`` at construction).

    Use :meth:`status` for what the current step does (``"compiling"``), :meth:`update` after
    each step, :meth:`close` with the outcome. It is a context manager (``close()`` on exit).
    """

    def __init__(
        self,
        desc: str,
        total: int | None = None,
        *,
        initial: int = 0,
        unit: str = "epoch",
        show: bool | None = None,
        stream: TextIO | None = None,
    ):
        self.desc, self.total, self.n, self.unit = desc, total, initial, unit
        self.stream = sys.stderr if stream is None else stream
        self.mode: Mode = "off"
        if show is not False:
            self.mode = "bar" if interactive(self.stream) else "log"
        self.delay = FIRST if show else DELAY
        self.always = bool(show)  # a last line even for work shorter than the delay
        self.every = EVERY
        self._status = ""
        self._postfix = ""
        self._start = time.perf_counter()
        self._last_line: float | None = None  # when the last log line was written
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._bar: Any = None
        if self.mode == "bar" and (total is not None or show):
            self._open_bar()  # a fit's bar at once (as it always was); other work after DELAY
        self._thread = None
        if self.mode != "off":
            self._thread = threading.Thread(target=self._beat, name="ceemx-progress", daemon=True)
            self._thread.start()

    # -- what the work reports --------------------------------------------------------------------

    def status(self, text: str) -> None:
        """What runs now (shown beside the count until the next :meth:`update`)."""
        with self._lock:
            self._status = text
            if self._bar is not None:
                self._bar.set_postfix_str(self._line_postfix(), refresh=True)

    def update(self, n: int = 1, postfix: str = "") -> None:
        """``n`` more steps done; ``postfix``: the last step's numbers (``"J=5883.99"``)."""
        with self._lock:
            self.n += n
            self._status, self._postfix = "", postfix
            if self._bar is not None:
                self._bar.set_postfix_str(postfix, refresh=False)
                self._bar.update(n)

    def close(self, outcome: str | None = None) -> None:
        """End the display: the bar (or a last log line) says ``outcome`` (default ``"done"``).

        A log of work that never reached :data:`DELAY` writes nothing. Closing twice is a no-op.
        """
        if self._closed.is_set():
            return
        self._closed.set()
        if self._thread is not None:
            self._thread.join()
        outcome = outcome or "done"
        with self._lock:
            if self._bar is not None:
                self._bar.set_postfix_str(outcome, refresh=False)
                self._bar.close()
            elif self.mode == "log" and (self._last_line is not None or self.always):
                self._write(f"{outcome} ({_elapsed(time.perf_counter() - self._start)})")

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.close("interrupted" if issubclass(kind, KeyboardInterrupt) else "failed")

    # -- the display ------------------------------------------------------------------------------

    def _open_bar(self) -> None:
        from tqdm.auto import tqdm

        self._bar = tqdm(
            total=self.total,
            initial=self.n,
            desc=self.desc,
            unit=self.unit,
            leave=True,
            file=self.stream,
        )
        if self._status or self._postfix:
            self._bar.set_postfix_str(self._line_postfix(), refresh=True)

    def _line_postfix(self) -> str:
        return ", ".join(s for s in (self._postfix, self._status) if s)

    def _count(self) -> str:
        if self.total is None:
            return ""
        return f"{self.n}/{self.total} {self.unit}s"

    def _write(self, text: str) -> None:
        """One log line (the lock is held)."""
        try:
            self.stream.write(f"ceemx: {self.desc}: {text}\n")
            self.stream.flush()
        except (OSError, ValueError):  # a closed or broken stream: the work goes on
            self.mode = "off"
        self._last_line = time.perf_counter()

    def _beat(self) -> None:
        """The heartbeat: a bar's clock, and a log line when one is due."""
        while not self._closed.wait(_TICK):
            now = time.perf_counter()
            with self._lock:
                if self._closed.is_set():
                    return
                if self.mode == "bar":
                    if self._bar is None and now - self._start >= self.delay:
                        self._open_bar()
                    elif self._bar is not None:
                        self._bar.refresh()
                elif self.mode == "log" and self._log_due(now):
                    running = self._status or "running"
                    parts = [p for p in (self._count(), self._postfix, running) if p]
                    self._write(f"{', '.join(parts)} ({_elapsed(now - self._start)})")

    def _log_due(self, now: float) -> bool:
        if self._last_line is None:
            return now - self._start >= self.delay
        return now - self._last_line >= self.every


@contextlib.contextmanager
def task(desc: str, *, show: bool | None = None) -> Iterator[Progress]:
    """Progress of work without steps: shown only when it runs past :data:`DELAY` seconds.

    ``with task("diagnostics: 2 records"):`` around the work; the last log line says how long it
    took ("done"), or that it failed.
    """
    progress = Progress(desc, show=False if show is False else None, unit="")
    try:
        yield progress
    except BaseException:
        progress.close("interrupted" if sys.exc_info()[0] is KeyboardInterrupt else "failed")
        raise
    progress.close()
