"""One writer per checkpoint folder: an advisory lock held for a fit's lifetime.

Two fits writing one folder used to destroy each other's checkpoints (each save removes the
temporaries it finds, the other's among them: ``FileNotFoundError … .tmp-… -> state-8.eqx``).
:func:`folder_lock` takes an exclusive ``fcntl.flock`` lock on the file ``.lock`` in the folder,
without waiting; when another process (or another fit in this one) holds it, it raises at once,
before any compute, naming the holder from what the holder wrote into the file (pid, host, start
time). The kernel releases the lock when its holder exits, also on ``SIGKILL``, so a stale lock
never blocks a resume: a ``.lock`` left behind by a killed run is simply taken over. The file is
removed when the lock is released normally.

``flock`` locks are per open file: two fits in one process refuse each other too. Where
``fcntl`` is missing (Windows), no lock is taken.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import socket
import time
from collections.abc import Callable, Iterator

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

__all__ = ["LOCK_NAME", "folder_lock"]

#: the lock file's name in a checkpoint folder
LOCK_NAME = ".lock"


@contextlib.contextmanager
def folder_lock(folder: str, error: Callable[[str], Exception]) -> Iterator[None]:
    """Hold the exclusive lock of ``folder`` (which must exist) for the ``with`` block.

    Args:
        folder: the checkpoint folder.
        error: makes the exception raised when the folder is in use, from its message.

    Raises:
        The exception ``error`` makes — naming the folder and its writer (pid, host, start) —
        when another fit holds the lock.
    """
    if fcntl is None:  # pragma: no cover - Windows
        yield
        return
    path = os.path.join(folder, LOCK_NAME)
    fd = _acquire(path, error)
    try:
        yield
    finally:
        # Remove the file while still holding the lock: a process that opened it meanwhile
        # finds, once it gets the lock, that the path no longer names its file, and retries.
        with contextlib.suppress(OSError):
            os.remove(path)
        os.close(fd)


def _acquire(path: str, error: Callable[[str], Exception]) -> int:
    assert fcntl is not None
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise error(
                f"checkpoint folder {os.path.dirname(path)!r} is in use by another fit "
                f"({holder or 'its writer not yet recorded'}; lock file {path!r}): two fits "
                "writing one folder would destroy each other's checkpoints. Wait for it to "
                "finish, or pass another folder."
            ) from None
        except BaseException:
            os.close(fd)
            raise
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the holder removed the file we opened as it finished: lock the new one
    started = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    record = f"pid {os.getpid()} on host {socket.gethostname()}, started {started}"
    os.ftruncate(fd, 0)
    os.pwrite(fd, record.encode(), 0)
    return fd


def _holder(fd: int, wait: float = 1.0) -> str:
    """What the holder wrote into the lock file (it writes just after locking: wait ≤ 1 s)."""
    deadline = time.monotonic() + wait
    while True:
        text = ""
        with contextlib.suppress(OSError):
            text = os.pread(fd, 4096, 0).decode(errors="replace").strip()
        if text or time.monotonic() > deadline:
            return text
        time.sleep(0.01)
