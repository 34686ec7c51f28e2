"""How many CPU threads JAX's CPU runtime and the BLAS libraries use.

XLA's CPU runtime sizes its thread pool from the CPUs this process may run on (its affinity mask)
when the backend starts, and splits the work of each compiled program over those threads. On a
machine whose cores are busy with other work (a laptop running other jobs, several fits side by
side) that split backfires: threads wait for a sibling that the operating system has descheduled,
spinning meanwhile, and a program can take several times as long as pinned to one CPU.

:func:`limit_cpu_threads` restricts the process to its first ``n`` allowed CPUs before JAX
starts, which is the one control XLA honours (``XLA_FLAGS`` has no thread-count flag for the
runtime; ``taskset -c 0 python ...`` does the same from the shell). The library never calls it by
itself; the ``ceemx`` command does with ``--threads N`` or ``CEEMX_THREADS=N``.

:func:`blas_threads` is the other half: XLA's CPU LAPACK calls (Cholesky, triangular solves) run
in SciPy's OpenBLAS, which starts its own thread pool beside XLA's and keeps those threads
spinning after each call, on the cores XLA's threads need. ``fit``, ``smooth``, ``learn`` and
``estimate_noise`` run inside it (:func:`ceemx.infra.policy.entry_point`: the BLAS libraries at
one thread each for the duration of the call; ``CEEMX_BLAS_THREADS=N`` chooses another N, ``0``
leaves them as they are).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from typing import Any

from ceemx.infra.warn import warn
from ceemx.lib.typing import no_type_check

__all__ = ["blas_threads", "limit_cpu_threads"]

_controller: Any = None


def _blas_controller() -> Any:
    """The loaded BLAS libraries as threadpoolctl sees them (built once; ``False``: unavailable).

    SciPy's LAPACK module is imported first: it loads the OpenBLAS that XLA's CPU LAPACK kernels
    call, which JAX would otherwise load only at the first LAPACK program.
    """
    global _controller
    if _controller is None:
        try:
            import scipy.linalg  # noqa: F401  (loads the BLAS behind jaxlib's LAPACK kernels)
            from threadpoolctl import ThreadpoolController

            _controller = ThreadpoolController()
        except Exception:  # no threadpoolctl, or a BLAS it cannot read: leave the threads be
            _controller = False
    return _controller


_lock = threading.Lock()
_holders = 0  # blocks inside blas_threads now, in any thread
_limiter: Any = None  # the limit they share, restored when the last one leaves


def _release_openblas() -> None:
    """Let this thread set OpenBLAS's limit (threadpoolctl ≥ 3.6 lets one thread at a time)."""
    try:
        from threadpoolctl import OpenBLASController

        OpenBLASController.clear_controlling_thread(force=True)
    except (ImportError, AttributeError, TypeError):  # an older threadpoolctl: no such rule
        pass


@contextlib.contextmanager
def blas_threads(n: int | None = None) -> Iterator[None]:
    """Within the block, the BLAS libraries (OpenBLAS, MKL, BLIS) run at most ``n`` threads.

    ``None``: ``CEEMX_BLAS_THREADS`` if set (``0``: no limit), else 1. OpenBLAS's limit is the
    process's, not a thread's: blocks open at once in several threads (fits run from a thread
    pool) share the first one's limit, and the libraries' own settings come back when the last
    of them leaves, whatever the order — restoring per block would let the first to leave lift
    the limit under the others, and the last one's restore set the limit for good. Nested blocks
    are fine.
    """
    global _holders, _limiter
    if n is None:
        text = os.environ.get("CEEMX_BLAS_THREADS", "").strip()
        n = int(text) if text.isdigit() else 1
    controller = _blas_controller() if n > 0 else False
    if not controller:
        yield
        return
    with _lock:
        if _holders == 0:
            _release_openblas()
            _limiter = controller.limit(limits=n, user_api="blas")  # set now; restored below
            _release_openblas()  # no thread keeps control between our calls
        _holders += 1
    try:
        yield
    finally:
        with _lock:
            _holders -= 1
            if _holders == 0:
                _release_openblas()
                _limiter.restore_original_limits()
                _release_openblas()
                _limiter = None


@no_type_check  # validates its argument
def limit_cpu_threads(n: int) -> int:
    """Run this process (and the threads it starts from now on) on at most ``n`` CPUs.

    Call it before JAX's first computation: XLA sizes its CPU thread pool then. Called later, it
    still pins the calling thread, but the pool keeps its size (a warning says so).

    Args:
        n: the number of CPUs (≥ 1); more than the process may use is capped.

    Returns:
        The number of CPUs the process now runs on.

    Raises:
        ValueError: ``n`` is not an integer ≥ 1.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"`n` must be an integer >= 1; got {n!r}.")
    if not (hasattr(os, "sched_getaffinity") and hasattr(os, "sched_setaffinity")):
        warn(
            "limiting CPU threads needs CPU affinity (Linux); not available here: the limit is "
            "ignored."
        )
        return os.cpu_count() or 1
    if _jax_started():
        warn(
            "JAX's backend is already running, so its CPU thread pool keeps its size: limit the "
            "threads before the first computation (or start Python under `taskset`)."
        )
    cpus = sorted(os.sched_getaffinity(0))[:n]
    os.sched_setaffinity(0, cpus)
    return len(cpus)


def _jax_started() -> bool:
    """Whether JAX's backends exist already (JAX has no public query; False when unknown)."""
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this internal: no warning
        return False
