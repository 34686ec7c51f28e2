"""Data parallelism: the trajectory (batch) axis spread over several devices.

Every compiled step of a fit maps (``vmap``) over the B trajectories and sums their Gauss–Newton
terms, so placing the batch-axis arrays — ``y``, ``u``, ``mask`` and the (B, T, n) states — with a
:class:`jax.sharding.NamedSharding` over a 1-D mesh named ``"batch"`` is enough: XLA's SPMD
partitioner splits the per-trajectory work between the devices and inserts the all-reduces of the
sums. The algorithm is unchanged; only the summation order of the cross-trajectory sums differs
(answers agree to rounding). ``ceemx.fit(..., devices="all")`` does this for you::

    result = ceemx.fit(guess, data, solver=ceemx.JointLM(), devices="all")

or by hand, for :func:`ceemx.smooth` and the other batch functions::

    mesh = batch_mesh()
    data, x0 = shard_batch(data, x0, mesh)
    sol = ceemx.smooth(system, data, x0)

**B not divisible by the device count.** Padding the batch with dummy trajectories would change
the objective, so it is never done. By default the arrays are placed on the first ``k`` devices of
the mesh, ``k`` the largest divisor of B not above the device count (B = 12 on 8 devices: 6
devices; a prime B larger than the device count: one device). ``strict=True`` raises a
``ValueError`` naming B and the device count instead. Choose B a multiple of the device count to
use them all. When ``fit`` excludes outlying trajectories at the start, the remaining ones stay
on the same devices, placed as XLA partitions the subset.

**Several processes** (hosts, or processes on one machine; :mod:`ceemx.infra.distributed`). Each
process calls :func:`ceemx.infra.distributed.initialize` (a wrapper of
:func:`jax.distributed.initialize` that reads ``CEEMX_COORDINATOR``, ``CEEMX_NUM_PROCESSES``,
``CEEMX_PROCESS_ID`` and selects Gloo CPU collectives) before anything else touches JAX;
:func:`jax.devices` then lists every process's devices, so ``"all"`` and :func:`batch_mesh` span
them all. Every process runs the same program on the same *whole* data set (same files, same
seeds) and start: :func:`shard_batch` hands JAX its host copies and each process transfers only
the shards of its own devices. It checks first that the copies agree (a SHA-256 digest per array,
gathered: a ``ValueError`` names the array and the processes that differ) and that B is a
multiple of the device count (no fallback to fewer devices across processes). ``fit`` reads
per-trajectory values on the host every epoch through
:func:`ceemx.infra.distributed.to_host` (gathered across processes, the same collective on every
process); only process 0 shows progress and writes checkpoints (every process reads one to
resume: a folder all of them see); the result is gathered, so every process gets the whole
:class:`~ceemx.FitResult`, fully addressable, as a one-process fit's. θ and J equal a one-process
fit's to rounding (two processes: ``tests/test_distributed.py``).

"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import ArrayLike

from ceemx.data.trajectories import Trajectories
from ceemx.infra.distributed import check_same, to_host

__all__ = ["BATCH_AXIS", "batch_mesh", "resolve_devices", "shard_batch"]

BATCH_AXIS = "batch"


def batch_mesh(devices: Sequence[Any] | None = None) -> Mesh:
    """A 1-D :class:`jax.sharding.Mesh` named ``"batch"`` over ``devices``.

    Args:
        devices: the devices (default :func:`jax.devices`: every device of the default backend,
            of all hosts after :func:`jax.distributed.initialize`).

    Raises:
        ValueError: for an empty device list.
    """
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("`devices` is empty: a mesh needs at least one device.")
    return Mesh(np.asarray(devs, dtype=object), (BATCH_AXIS,))


def resolve_devices(devices) -> Mesh | None:
    """``fit``'s ``devices`` argument as a mesh: ``None`` → ``None``, ``"all"`` → all devices.

    ``"all"`` is every process's devices after :func:`jax.distributed.initialize` (see "Several
    processes" in the module docstring).

    Raises:
        TypeError: for anything but ``None``, ``"all"`` or a 1-D :class:`jax.sharding.Mesh`.
    """
    if devices is None:
        return None
    if isinstance(devices, str) and devices == "all":
        mesh = batch_mesh()
    elif isinstance(devices, Mesh):
        if devices.devices.ndim != 1:
            raise TypeError(
                f"`devices` must be a 1-D mesh (the batch axis); got axes {devices.axis_names} "
                f"of shape {devices.devices.shape}."
            )
        mesh = devices
    else:
        raise TypeError(f'`devices` must be None, "all" or a jax.sharding.Mesh; got {devices!r}.')
    return mesh


def _submesh(mesh: Mesh, B: int, strict: bool) -> Mesh:
    """``mesh`` cut to its first k devices, k the largest divisor of B not above its size."""
    if mesh.devices.ndim != 1:
        raise ValueError(f"`mesh` must be 1-D; got shape {mesh.devices.shape}.")
    n = mesh.devices.size
    if B % n == 0:
        return mesh
    if mesh.is_multi_process:
        raise ValueError(
            f"the batch size B = {B} is not divisible by the {n} devices of a mesh over "
            f"{len({d.process_index for d in mesh.devices.flat})} processes: every process must "
            f"hold an equal share of the trajectories; use B a multiple of {n}."
        )
    if strict:
        raise ValueError(
            f"the batch size B = {B} is not divisible by the {n} devices of the mesh; use B a "
            f"multiple of {n}, a mesh of fewer devices, or strict=False (the largest divisor "
            "of B)."
        )
    k = max(d for d in range(1, n + 1) if B % d == 0)
    return Mesh(mesh.devices[:k], mesh.axis_names)


def shard_batch(
    data: Trajectories, states: ArrayLike, mesh: Mesh, *, strict: bool = False
) -> tuple[Trajectories, jax.Array]:
    """``data`` and the (B, T, n) ``states`` placed with their batch axis split over ``mesh``.

    The leading axis of ``y``, ``u``, ``mask`` and ``states`` is sharded over the mesh's one axis;
    the other axes are replicated. Values are unchanged.

    Args:
        data: B trajectories.
        states: (B, T, n) states.
        mesh: a 1-D mesh (:func:`batch_mesh`).
        strict: raise when B is not divisible by the device count, instead of using the largest
            divisor of B (see the module docstring).

    Returns:
        ``(data, states)``, sharded.

    Raises:
        ValueError: with ``strict``, naming B and the device count when they do not divide; for a
            mesh that is not 1-D or ``states`` whose batch size is not B.
    """
    B = data.batch_size
    if np.shape(states)[0] != B:
        raise ValueError(f"`states` has batch size {np.shape(states)[0]} but `data` has B = {B}.")
    mesh = _submesh(mesh, B, strict)
    spec = NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))
    arrays = (data.y, data.u, data.mask, states)
    if mesh.is_multi_process:
        # Each process hands over its host copy of the whole batch; it must be everyone's.
        arrays = tuple(to_host(a) for a in arrays)
        check_same("data", y=arrays[0], u=arrays[1], mask=arrays[2])
        check_same("states", states=arrays[3])
    else:
        arrays = tuple(jnp.asarray(a) for a in arrays)
    y, u, mask, x = jax.device_put(arrays, spec)
    return eqx.tree_at(lambda d: (d.y, d.u, d.mask), data, (y, u, mask)), x
