"""Several processes, one fit: :func:`jax.distributed` set-up, host reads and a local launcher.

A fit can run as N processes (one per host, or several on one machine), the trajectories split
over every process's devices (:mod:`ceemx.data.sharding`, ``fit(devices="all")``). Each process
runs the same script on the same whole data set; before any JAX work it calls
:func:`initialize`::

    import ceemx
    ceemx.infra.distributed.initialize()   # from CEEMX_COORDINATOR, _NUM_PROCESSES, _PROCESS_ID
    ...
    result = ceemx.fit(guess, data, solver=ceemx.JointLM(), devices="all")

and is started by the launcher, here two processes on this machine::

    python -m ceemx.infra.distributed -n 2 my_fit.py [args...]

(or by hand, one command per process, with the three variables set). On CPU the processes
exchange the cross-trajectory sums through Gloo (``jax_cpu_collectives_implementation``, set by
:func:`initialize`); on GPUs through NCCL.

A global array (one split over the devices of several processes) cannot be read on one host:
:func:`to_host` gathers it (a collective: every process must call it, in the same order — as they
do, running the same program) and reads any other array as :func:`numpy.asarray` does.
:func:`check_same` compares host data between processes (a digest each) and names what differs.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

__all__ = [
    "ENV_COORDINATOR",
    "ENV_NUM_PROCESSES",
    "ENV_PROCESS_ID",
    "check_same",
    "free_port",
    "initialize",
    "is_main_process",
    "launch",
    "to_host",
]

ENV_COORDINATOR = "CEEMX_COORDINATOR"
ENV_NUM_PROCESSES = "CEEMX_NUM_PROCESSES"
ENV_PROCESS_ID = "CEEMX_PROCESS_ID"


def _env_int(name: str) -> int | None:
    value = os.environ.get(name)
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError:
        raise ValueError(
            f"environment variable {name} must be an integer; got {value!r}."
        ) from None


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    cpu_collectives: str = "gloo",
) -> int:
    """Join this process to a multi-process JAX run; call it before any other JAX work.

    Wraps :func:`jax.distributed.initialize`. Arguments left ``None`` are read from the
    environment: ``CEEMX_COORDINATOR`` (``host:port`` of process 0's coordinator),
    ``CEEMX_NUM_PROCESSES`` and ``CEEMX_PROCESS_ID`` (set by the launcher,
    ``python -m ceemx.infra.distributed``). When none of the three is given anywhere, nothing is
    done and 0 is returned: the same script runs as a single process. It also selects the CPU
    collectives (``jax_cpu_collectives_implementation``, default Gloo: without them a CPU
    computation over several processes fails); GPUs use NCCL regardless.

    Args:
        coordinator_address: ``host:port`` where process 0 serves the coordinator.
        num_processes: the number of processes, ≥ 1.
        process_id: this process's index in ``0 … num_processes − 1``.
        cpu_collectives: ``"gloo"`` (default) or ``"mpi"``.

    Returns:
        This process's index (:func:`jax.process_index`).

    Raises:
        ValueError: naming the argument (or its environment variable) when it is missing, not an
            integer or out of range — before JAX is touched.
    """
    coordinator_address = coordinator_address or os.environ.get(ENV_COORDINATOR) or None
    num_processes = _env_int(ENV_NUM_PROCESSES) if num_processes is None else num_processes
    process_id = _env_int(ENV_PROCESS_ID) if process_id is None else process_id
    given = {
        "coordinator_address": coordinator_address,
        "num_processes": num_processes,
        "process_id": process_id,
    }
    if all(v is None for v in given.values()):
        return 0
    env = {
        "coordinator_address": ENV_COORDINATOR,
        "num_processes": ENV_NUM_PROCESSES,
        "process_id": ENV_PROCESS_ID,
    }
    missing = [f"`{k}` (or {env[k]})" for k, v in given.items() if v is None]
    if missing:
        raise ValueError(
            f"initialize needs all three of its arguments; missing {', '.join(missing)}."
        )
    for name in ("num_processes", "process_id"):
        value = given[name]
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"`{name}` must be an int; got {value!r}.")
    assert num_processes is not None and process_id is not None  # for the type checker
    if num_processes < 1:
        raise ValueError(f"`num_processes` must be >= 1; got {num_processes}.")
    if not 0 <= process_id < num_processes:
        raise ValueError(f"`process_id` must be in 0 … {num_processes - 1}; got {process_id}.")
    if not isinstance(coordinator_address, str) or ":" not in coordinator_address:
        raise ValueError(f"`coordinator_address` must be 'host:port'; got {coordinator_address!r}.")
    if cpu_collectives not in ("gloo", "mpi"):
        raise ValueError(f"`cpu_collectives` must be 'gloo' or 'mpi'; got {cpu_collectives!r}.")
    jax.config.update("jax_cpu_collectives_implementation", cpu_collectives)
    jax.distributed.initialize(
        coordinator_address=coordinator_address,
        num_processes=int(num_processes),
        process_id=int(process_id),
    )
    return jax.process_index()


def is_main_process() -> bool:
    """Whether this is process 0 (the one that prints and writes; always so in a single process)."""
    return jax.process_index() == 0


def to_host(x: Any) -> np.ndarray:
    """``x`` as a NumPy array on this host, gathered from every process when it spans several.

    An array whose shards all lie on this process's devices, or that is replicated, is read as
    :func:`numpy.asarray` reads it (no communication). A global array split over several
    processes is gathered with :func:`jax.experimental.multihost_utils.process_allgather` — a
    collective that every process must reach with the same array.
    """
    if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def _digest(a: Any) -> bytes:
    a = np.ascontiguousarray(to_host(a))
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.digest()


def check_same(what: str, **arrays: Any) -> None:
    """Raise when an array differs between the processes (a no-op in a single process).

    Each process hashes its host copies (SHA-256 of dtype, shape and bytes) and the digests are
    gathered; every process raises the same error.

    Args:
        what: what the arrays are, for the message (``"data"``).
        **arrays: the arrays by name (``y=..., u=...``); ``None`` values are skipped.

    Raises:
        ValueError: naming ``what``, the array and the processes whose copy differs from
            process 0's.
    """
    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    names = [k for k, v in arrays.items() if v is not None]
    mine = np.frombuffer(b"".join(_digest(arrays[k]) for k in names), np.uint8)
    every = np.asarray(multihost_utils.process_allgather(mine)).reshape(-1, len(names), 32)
    for i, name in enumerate(names):
        differ = [p for p in range(every.shape[0]) if not np.array_equal(every[p, i], every[0, i])]
        if differ:
            raise ValueError(
                f"`{what}` differs between processes: `{name}` of process"
                f"{'es' if len(differ) > 1 else ''} {', '.join(map(str, differ))} is not "
                "process 0's. Every process of a multi-process fit passes the same whole data "
                "set and start (same files, same seeds); fit splits the trajectories over the "
                "processes' devices itself."
            )


def free_port() -> int:
    """A TCP port on this machine that was free a moment ago (for a local coordinator)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def launch(
    command: Sequence[str],
    num_processes: int,
    *,
    port: int | None = None,
    timeout: int | float | None = None,
    env: dict[str, str] | None = None,
) -> list[int]:
    """Run ``command`` as ``num_processes`` local processes joined by :func:`initialize`.

    Each process gets ``CEEMX_COORDINATOR=127.0.0.1:port``, ``CEEMX_NUM_PROCESSES`` and its
    ``CEEMX_PROCESS_ID``, and inherits stdout and stderr. When one process fails the others are
    terminated (a collective would otherwise wait for it for ever).

    Args:
        command: the program and its arguments (``[sys.executable, "fit.py"]``).
        num_processes: how many processes, ≥ 1.
        port: the coordinator's port (default: a free one).
        timeout: seconds before every process still running is killed (default: none).
        env: the environment (default: this process's).

    Returns:
        The processes' exit codes, process 0 first (−9 for one killed at the timeout).

    Raises:
        ValueError: for an empty command or ``num_processes`` < 1.
    """
    if not command:
        raise ValueError("`command` is empty.")
    if isinstance(num_processes, bool) or not isinstance(num_processes, int) or num_processes < 1:
        raise ValueError(f"`num_processes` must be an int >= 1; got {num_processes!r}.")
    port = free_port() if port is None else port
    base = dict(os.environ if env is None else env)
    base.update({ENV_COORDINATOR: f"127.0.0.1:{port}", ENV_NUM_PROCESSES: str(num_processes)})
    procs = [
        subprocess.Popen(list(command), env={**base, ENV_PROCESS_ID: str(i)})
        for i in range(num_processes)
    ]
    deadline = None if timeout is None else time.monotonic() + timeout
    try:
        while any([p.poll() is None for p in procs]):  # a list: poll every process
            failed = any(p.returncode not in (None, 0) for p in procs)
            late = deadline is not None and time.monotonic() > deadline
            if failed or late:
                for p in procs:
                    if p.poll() is None:
                        p.kill()
            time.sleep(0.05)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return [int(p.returncode) for p in procs]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m ceemx.infra.distributed -n N script.py [args]``: N local processes."""
    ap = argparse.ArgumentParser(
        prog="python -m ceemx.infra.distributed",
        description="Run a Python script as N local processes of one JAX multi-process run "
        "(the script calls ceemx.infra.distributed.initialize() before any JAX work).",
    )
    ap.add_argument("-n", "--processes", type=int, default=2, help="number of processes (2)")
    ap.add_argument("--port", type=int, default=None, help="coordinator port (a free one)")
    ap.add_argument("--timeout", type=float, default=None, help="seconds before all are killed")
    ap.add_argument("script", help="the Python script")
    ap.add_argument("args", nargs=argparse.REMAINDER, help="the script's arguments")
    ns = ap.parse_args(argv)
    codes = launch(
        [sys.executable, ns.script, *ns.args], ns.processes, port=ns.port, timeout=ns.timeout
    )
    bad = [(i, c) for i, c in enumerate(codes) if c != 0]
    for i, c in bad:
        print(f"process {i} exited with status {c}", file=sys.stderr)
    return 0 if not bad else (bad[0][1] if bad[0][1] > 0 else 1)


if __name__ == "__main__":
    sys.exit(main())
