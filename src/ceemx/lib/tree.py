"""Pytree utilities for solver objects."""

from __future__ import annotations

from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.core import Tracer

__all__ = ["as_jax", "is_weak", "trace_numbers", "value_repr"]

_T = TypeVar("_T")

SHOWN_SIZE = 25  # arrays up to this many entries print their values; larger ones their shape


class _Values:
    """A leaf that prints as its values (``0.05``, ``[0.1, 0.2]``)."""

    def __init__(self, values: np.ndarray):
        self.values = values

    def __repr__(self) -> str:
        if self.values.ndim == 0:
            value = self.values.item()
            return repr(value) if isinstance(value, bool) else f"{value:.6g}"
        return np.array2string(
            self.values, separator=", ", formatter={"float_kind": lambda v: f"{v:.6g}"}
        )


def value_repr(module: Any, size: int = SHOWN_SIZE) -> str:
    """``module`` as Equinox prints it, with the values of its small concrete arrays.

    Equinox prints every array as its dtype and shape (``scale=f64[]``), which hides what an
    identified model learned. Here arrays of at most ``size`` entries print their values
    (``scale=0.0123``, ``k=[0.23, 0.017]``); larger ones (network weights) and traced values
    keep the short form.
    """
    import equinox as eqx

    def shown(leaf):
        if isinstance(leaf, Tracer) or not isinstance(leaf, jax.Array | np.ndarray):
            return leaf
        if leaf.size > size:
            return leaf
        try:  # an array spread over processes is not readable here: its short form
            return _Values(np.asarray(leaf))
        except RuntimeError:
            return leaf

    return eqx.tree_pformat(jtu.tree_map(shown, module))


def trace_numbers(tree: _T, dtype) -> _T:
    """Python ``float`` leaves of ``tree`` as 0-d arrays of ``dtype``.

    ``eqx.filter_jit`` treats Python numbers as static, so a solver object whose tolerances or
    trust-region weights are floats would compile again for every new value. Entry points convert
    them once; booleans and integers (which change the program: bounds, switches) are left alone,
    as are static fields (not leaves).
    """

    def convert(leaf):
        if isinstance(leaf, float):
            return jnp.asarray(leaf, dtype)
        return leaf

    return jtu.tree_map(convert, tree)


def is_weak(leaf) -> bool:
    """Whether ``leaf`` is a weakly typed JAX array (e.g. ``jnp.asarray(0.1)``).

    JAX keys compiled programs on weak types: a weak and a strong copy of one system trace and
    compile every program twice, so entry points make such leaves strong.
    """
    return bool(getattr(leaf, "weak_type", False))


def as_jax(a: Any) -> jax.Array:
    """``jnp.asarray(a)``, without compiling a program for a NumPy array.

    JAX 0.10's ``jnp.asarray`` of a NumPy array without a ``dtype`` goes through a compiled
    identity (``lax.stage``): one XLA program per new shape and dtype, far slower than a
    transfer. NumPy arrays and scalars are transferred
    (``jax.device_put``, which canonicalises the dtype as ``asarray`` does); anything else goes
    to ``jnp.asarray``.
    """
    if isinstance(a, (np.ndarray, np.generic)):
        return jax.device_put(a)
    return jnp.asarray(a)
