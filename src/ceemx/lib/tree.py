"""Pytree utilities for solver objects."""

from __future__ import annotations

from typing import TypeVar

import jax.numpy as jnp
import jax.tree_util as jtu

__all__ = ["is_weak", "trace_numbers"]

_T = TypeVar("_T")


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
