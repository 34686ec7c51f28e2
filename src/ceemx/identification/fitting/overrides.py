"""Per-fit bounds and fixed values: ``fit(..., bounds={"k": (0, 10)}, fixed={"g": 9.81})``.

A class declares what a parameter may be (:func:`ceemx.param`: ``positive=True``, ``lower=``,
``fixed=True``); a fit may narrow that without editing the class (MATLAB's
``Parameters(i).Minimum/Maximum/Fixed``, dynamax's per-instance properties):

- ``bounds={name: (lower, upper)}`` — the field is learned inside (lower, upper) for this fit
  (``None`` for an open end): its constraint becomes :class:`~ceemx.models.constraints.Interval`,
  ``GreaterThan`` or ``LessThan`` (:mod:`ceemx.models.constraints`), and the summary's
  constraint column says so. The bounds may only narrow the class's: a class that says
  ``positive=True`` takes ``(0, 10)`` or ``(1, None)``, not ``(-1, 1)`` (a fitted model must
  still be a valid instance of its class).
- ``fixed={name: value}`` — the field is held at ``value`` for this fit (``None``: at its
  current value); the result's system holds that value.

Names are the fields as the summary writes them (``k``, ``physics.k``, ``obs_noise.scale``), a
whole field at a time: an element (``H[0,1]``) is refused with a message (θ holds whole arrays).
The per-fit constraints travel with the fit's options to every problem it builds
(:meth:`ceemx.identification.problem.FitProblem.create`, ``overrides``).
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.tree_util as jtu
import numpy as np

from ceemx.identification.fitting.fit_options import FitOptions
from ceemx.lib.tree import as_jax
from ceemx.models.constraints import (
    AbstractConstraint,
    Fixed,
    GreaterThan,
    Interval,
    LessThan,
    Unconstrained,
    leaf_constraints,
)
from ceemx.models.parameter_meta import Overrides, leaf_names
from ceemx.models.system import AbstractSystem

__all__ = ["apply_overrides", "with_overrides"]

_ELEMENT = re.compile(r"^(?P<field>.+)\[(?P<index>[\d, ]+)\]$")


def _leaf_index(system: AbstractSystem, name: str, what: str) -> int:
    names = leaf_names(system)
    leaves = jtu.tree_leaves(system)
    if name in names and eqx.is_inexact_array(leaves[names.index(name)]):
        return names.index(name)
    element = _ELEMENT.match(name)
    if element and element["field"] in names:
        field = element["field"]
        raise ValueError(
            f"`{what}`: {name!r} is one element of {field!r}; bounds and fixed values apply to "
            f"a whole field (give {field!r}; to hold a single element, make it a field of its "
            "own)."
        )
    learnable = [n for n, leaf in zip(names, leaves, strict=True) if eqx.is_inexact_array(leaf)]
    shown = ", ".join(learnable[:12]) + (", …" if len(learnable) > 12 else "")
    raise ValueError(f"`{what}`: the system has no parameter {name!r} (its parameters: {shown}).")


def _end(value: Any, name: str, which: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"`bounds[{name!r}]`: the {which} bound must be a number or None.")
    value = float(value)
    if math.isnan(value):
        raise ValueError(f"`bounds[{name!r}]`: the {which} bound is NaN.")
    return None if math.isinf(value) else value


def _bounded(name: str, pair: Any) -> AbstractConstraint:
    if not isinstance(pair, tuple | list) or len(pair) != 2:
        raise TypeError(f"`bounds[{name!r}]` must be a pair (lower, upper); got {pair!r}.")
    lower, upper = _end(pair[0], name, "lower"), _end(pair[1], name, "upper")
    if lower is not None and upper is not None:
        if not lower < upper:
            raise ValueError(f"`bounds[{name!r}]`: lower {lower:g} must be below upper {upper:g}.")
        return Interval(lower, upper)
    if lower is not None:
        return GreaterThan(lower)
    if upper is not None:
        return LessThan(upper)
    return Unconstrained()


def apply_overrides(
    system: AbstractSystem,
    bounds: Mapping[str, Any] | None,
    fixed: Mapping[str, Any] | None,
) -> tuple[AbstractSystem, Overrides]:
    """The system with its fixed values set, and the per-fit constraints (module notes).

    Raises:
        TypeError: ``bounds`` or ``fixed`` not a mapping, a bound not a number.
        ValueError: an unknown name or an element, a name in both, bounds reaching outside the
            class's constraint or not containing the current value, a fixed value of another
            shape or outside the class's constraint.
    """
    overrides: list[tuple[str, AbstractConstraint]] = []
    for what, given in (("bounds", bounds), ("fixed", fixed)):
        if given is not None and not isinstance(given, Mapping):
            raise TypeError(f"`{what}` must be a dict of parameter names; got {given!r}.")
    bounds, fixed = dict(bounds or {}), dict(fixed or {})
    both = sorted(set(bounds) & set(fixed))
    if both:
        raise ValueError(f"{both[0]!r} is both bounded and fixed: give it in one of the two.")
    names = leaf_names(system)
    classes = leaf_constraints(system)
    leaves = jtu.tree_leaves(system)
    for name, pair in bounds.items():
        i = _leaf_index(system, name, "bounds")
        declared, c = classes[i], _bounded(name, pair)
        if not declared.trainable:
            raise ValueError(f"`bounds`: {name!r} is declared fixed in its class (ceemx.param).")
        lo, hi = c.bounds
        class_lo, class_hi = declared.bounds
        if lo < class_lo or hi > class_hi:
            raise ValueError(
                f"`bounds[{name!r}]` = {tuple(pair)!r} reaches outside its class's constraint "
                f"({declared.description}): per-fit bounds can only narrow it."
            )
        value = np.asarray(leaves[i])
        if not np.all(c.contains(value)):
            raise ValueError(
                f"`bounds[{name!r}]` = {tuple(pair)!r} does not contain its start value "
                f"{value.tolist()!r}: start inside the bounds."
            )
        overrides.append((name, c))
    for name, value in fixed.items():
        i = _leaf_index(system, name, "fixed")
        old = leaves[i]
        if value is not None:
            new = np.asarray(value, dtype=np.asarray(old).dtype)
            if new.shape != np.shape(old):
                new = np.broadcast_to(new, np.shape(old)) if new.ndim == 0 else new
            if new.shape != np.shape(old):
                raise ValueError(
                    f"`fixed[{name!r}]` has shape {new.shape}; the parameter's is {np.shape(old)}."
                )
            if not np.all(classes[i].contains(new)):
                raise ValueError(
                    f"`fixed[{name!r}]` = {value!r} lies outside its class's constraint "
                    f"({classes[i].description})."
                )
            leaves = list(leaves)
            leaves[i] = as_jax(new)
        overrides.append((name, Fixed()))
    system = jtu.tree_unflatten(jtu.tree_structure(system), leaves)
    assert names == leaf_names(system)
    return system, tuple(overrides)


def with_overrides(
    system: AbstractSystem,
    options: FitOptions,
    bounds: Mapping[str, Any] | None,
    fixed: Mapping[str, Any] | None,
) -> tuple[AbstractSystem, FitOptions]:
    """:func:`apply_overrides` for :func:`ceemx.fit`: the system and options the fit runs with."""
    if bounds is None and fixed is None:
        return system, options
    system, overrides = apply_overrides(system, bounds, fixed)
    return system, dataclasses.replace(options, overrides=overrides)
