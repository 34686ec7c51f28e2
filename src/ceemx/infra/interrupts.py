"""How the ``ceemx`` command ends on SIGINT or SIGTERM: one line, an exit status, no traceback.

:class:`Interrupts` turns either signal into one line on stderr (``ceemx: interrupted``,
``ceemx: terminated``) and ``os._exit(128 + signal)`` — 130 or 143 — from anywhere, removing the
``--out`` folders the run created if they are still empty; inside :meth:`Interrupts.critical`
(writing the results) the exit waits for the block's end. A light module (standard library
only): the command installs it before importing JAX.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from typing import Any

__all__ = ["EXIT_INTERRUPTED", "INTERRUPTED", "Interrupts", "missing_folders"]

#: the line a command interrupted by SIGINT prints on stderr
INTERRUPTED = b"ceemx: interrupted\n"
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report an interrupted command
#: the signals the command turns into one line and exit status 128 + signal number
_SIGNALS: dict[int, bytes] = {
    signal.SIGINT: b"ceemx: interrupted\n",
    signal.SIGTERM: b"ceemx: terminated\n",
}


class Interrupts:
    """SIGINT or SIGTERM → one line on stderr and ``os._exit(128 + signal)``, from anywhere.

    Before exiting, the folders listed in ``created`` (made by this run for ``--out``) are removed
    if they are still empty.

    ``os._exit`` skips interpreter shutdown: a ``KeyboardInterrupt`` unwinding through JAX while
    XLA's compiler threads run (and the teardown that follows) is what printed long tracebacks
    and sometimes crashed. The exit is taken by the first of two routes: the Python-level handler
    (runs in the main thread between bytecodes) and a watcher thread woken through
    :func:`signal.set_wakeup_fd` (runs even while the main thread is inside a long C++ call such as
    an XLA compilation). Inside :meth:`critical` (writing the results) the exit waits until the
    block ends, so that files are either all written or not at all.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._critical = 0
        self._pending: int | None = None
        self._exiting = False
        self._old_handlers: dict[int, Any] = {}
        self._old_wakeup = -1
        self._pipe: tuple[int, int] | None = None
        self.created: list[str] = []

    def install(self) -> None:
        """Take over SIGINT and SIGTERM (main thread only), with the watcher thread."""
        for signum in _SIGNALS:
            self._old_handlers[signum] = signal.signal(signum, self._on_signal)
        r, w = os.pipe()
        os.set_blocking(w, False)
        self._pipe = (r, w)
        self._old_wakeup = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        threading.Thread(target=self._watch, args=(r,), name="ceemx-sigint", daemon=True).start()

    def uninstall(self) -> None:
        """Give the signals back to their previous handlers; the watcher ends."""
        signal.set_wakeup_fd(self._old_wakeup)
        for signum, handler in self._old_handlers.items():
            signal.signal(signum, handler)
        if self._pipe is not None:
            os.close(self._pipe[1])  # the watcher reads EOF and ends; it closes the read end
            self._pipe = None

    def _watch(self, fd: int) -> None:
        try:
            while True:
                data = os.read(fd, 64)
                if not data:
                    return
                for signum in _SIGNALS:
                    if signum in data:
                        self._exit(signum)
        finally:
            with contextlib.suppress(OSError):
                os.close(fd)

    def _on_signal(self, signum, frame) -> None:
        self._exit(signum)

    def _exit(self, signum: int) -> None:
        with self._lock:
            if self._critical:
                self._pending = self._pending or signum
                return
            if self._exiting:
                return
            self._exiting = True
        _die(signum, self.created)

    def remove_created(self) -> None:
        """Remove the folders this run created for ``--out`` that are still empty."""
        for path in self.created:  # deepest first; a folder holding anything stays
            with contextlib.suppress(OSError):
                os.rmdir(path)

    @contextlib.contextmanager
    def critical(self) -> Iterator[None]:
        """A block that SIGINT or SIGTERM does not cut short (the exit follows the block)."""
        with self._lock:
            self._critical += 1
        try:
            yield
        finally:
            with self._lock:
                self._critical -= 1
                die = self._pending is not None and not self._critical and not self._exiting
                self._exiting = self._exiting or die
            if die:
                assert self._pending is not None
                _die(self._pending, self.created)


def _die(signum: int, created: Sequence[str] = ()) -> None:
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    for path in created:
        with contextlib.suppress(OSError):
            os.rmdir(path)
    with contextlib.suppress(OSError):
        os.write(2, _SIGNALS.get(signum, INTERRUPTED))
    os._exit(128 + int(signum))


def missing_folders(path: str) -> list[str]:
    """``path`` and its ancestors that do not exist yet, deepest first."""
    missing = []
    path = os.path.abspath(path)
    while not os.path.exists(path):
        missing.append(path)
        parent = os.path.dirname(path)
        if parent == path:
            break
        path = parent
    return missing
