"""Host-side array helpers of the data layer: conversion with readable errors, NumPy views.

What :class:`~ceemx.Trajectories` and :mod:`ceemx.data.checks` use to read a user's arrays on the
host (a ragged or string array named in the error, a cast that overflows refused) and to index
concrete CPU arrays with NumPy instead of compiling a small JAX program per shape.
"""

from __future__ import annotations

from typing import Any, TypeVar, cast

import jax
import numpy as np
from jax.core import Tracer

from ceemx.lib.tree import as_jax

_A = TypeVar("_A", jax.Array, np.ndarray)  # the kind of array given is the kind returned

__all__ = [
    "as_array",
    "as_numeric",
    "back_like",
    "cast_checked",
    "first_bad",
    "host_index",
    "indexed",
    "is_concrete",
    "on_host",
]


def is_concrete(a) -> bool:
    """Whether ``a`` is a value (not a tracer inside a transformation)."""
    return not isinstance(a, Tracer)


def on_host(tree) -> bool:
    """Whether every array leaf of ``tree`` may be indexed by NumPy instead of JAX.

    Eager JAX indexing compiles a small program per new shape (≈ 20 ms each); a NumPy view of a
    concrete array held on one CPU device gives the same values at no compile. Traced, sharded,
    accelerator-held (a round trip through the host) and weakly typed leaves (whose type a round
    trip through NumPy would not keep) stay with JAX.
    """
    for a in jax.tree_util.tree_leaves(tree):
        if isinstance(a, np.ndarray):
            continue
        if (
            not isinstance(a, jax.Array)
            or isinstance(a, Tracer)
            or a.weak_type
            or len(a.sharding.device_set) != 1
            or next(iter(a.sharding.device_set)).platform != "cpu"
        ):
            return False
    return True


def host_index(idx):
    """``idx`` for NumPy, or ``None`` where JAX indexes (traced, a list or tuple).

    An int, slice or NumPy array is kept, a concrete JAX array becomes a NumPy one; lists and
    tuples stay with JAX, which reads them its own way (a list is refused).
    """
    if isinstance(idx, Tracer):
        return None
    if isinstance(idx, jax.Array):
        return np.asarray(idx)
    if isinstance(idx, (slice, np.ndarray, int, np.integer)):
        return idx
    return None


def back_like(out: np.ndarray, like: _A) -> _A:
    """NumPy's result ``out`` as a JAX array placed as ``like`` is (a transfer, no program)."""
    if isinstance(like, np.ndarray):
        return cast(_A, out)
    if isinstance(like, jax.Array) and like.committed:
        return cast(_A, jax.device_put(out, like.sharding))
    return cast(_A, as_jax(out))


def indexed(a: _A, idx: Any) -> _A:
    """``a[idx]``: NumPy's indexing and a transfer for a concrete CPU array (:func:`on_host`).

    ``idx`` is what :func:`host_index` reads, or a tuple of such. Where NumPy refuses an index
    that JAX clamps, or ``a`` is traced, sharded or weakly typed, JAX indexes.
    """
    if isinstance(idx, tuple):
        parts = tuple(host_index(i) for i in idx)
        host_idx = None if any(p is None for p in parts) else parts
    else:
        host_idx = host_index(idx)
    if host_idx is not None and on_host(a):
        try:
            return back_like(np.asarray(a)[host_idx], a)
        except (IndexError, TypeError):
            pass
    return cast(_A, a[idx])


def first_bad(bad: np.ndarray) -> tuple[int, ...]:
    """The index of the first True entry of ``bad``."""
    return tuple(int(i) for i in np.argwhere(bad)[0])


def as_array(name: str, value) -> np.ndarray:
    """``np.asarray(value)``, with a ragged nesting reported as a ``ValueError`` naming ``name``."""
    try:
        return np.asarray(value)
    except ValueError as err:  # NumPy refuses ragged nested sequences
        raise ValueError(
            f"`{name}` must be a rectangular array; got a ragged sequence ({err})."
        ) from None


def as_numeric(name: str, value) -> np.ndarray:
    """``value`` as a real numeric NumPy array (bool, integer or floating), else ``TypeError``."""
    a = as_array(name, value)
    if np.issubdtype(a.dtype, np.complexfloating):
        raise TypeError(f"`{name}` must be real; got complex dtype {a.dtype}.")
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise TypeError(f"`{name}` must be a numeric array; got dtype {a.dtype}.")
    return a


def cast_checked(name: str, a: np.ndarray, dtype, where: np.ndarray | None = None) -> np.ndarray:
    """``a`` cast to ``dtype``, raising ``ValueError`` where a finite value overflows the cast.

    Args:
        name: the argument, for the message.
        a: a real NumPy array.
        dtype: the target floating-point dtype.
        where: optional booleans broadcastable to ``a``; only these entries are checked.
    """
    dtype = np.dtype(dtype)
    if a.dtype == dtype:
        return a
    with np.errstate(over="ignore", invalid="ignore"):
        out = a.astype(dtype)
    overflow = np.isfinite(a) & ~np.isfinite(out)
    if where is not None:
        overflow = overflow & where
    if overflow.any():
        idx = tuple(int(i) for i in np.argwhere(overflow)[0])
        raise ValueError(
            f"`{name}` has the value {a[idx]} at index {list(idx)}, which overflows {dtype} "
            f"(largest finite value {np.finfo(dtype).max})."
        )
    return out
