"""How many CPU threads JAX's CPU runtime uses (opt-in; the ``ceemx`` command's ``--threads``).

XLA's CPU runtime sizes its thread pool from the CPUs this process may run on (its affinity mask)
when the backend starts, and splits the work of each compiled program over those threads. On a
machine whose cores are busy with other work (a laptop running other jobs, several fits side by
side) that split backfires: threads wait for a sibling that the operating system has descheduled,
spinning meanwhile. Measured on the 2-core development machine with two other busy processes: a
joint iteration of the demo problem took 1.7–6.5 s with the default two threads against 0.6 s
pinned to one CPU, and 0.35 s on the idle machine (``benchmarks/README.md``, "Busy machines").

:func:`limit_cpu_threads` restricts the process to its first ``n`` allowed CPUs before JAX
starts, which is the one control XLA honours (``XLA_FLAGS`` has no thread-count flag for the
runtime; ``taskset -c 0 python ...`` does the same from the shell). The library never calls it by
itself; the ``ceemx`` command does with ``--threads N`` or ``CEEMX_THREADS=N``.
"""

from __future__ import annotations

import os

from ceemx.infra.warn import warn
from ceemx.lib.typing import no_type_check

__all__ = ["limit_cpu_threads"]


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
