"""What a parameter's field says besides its value: names, per-fit constraints, units.

- :func:`leaf_names` — each leaf's name as written (``k``, ``physics.k``, ``obs_noise.scale``);
- :data:`Overrides` and :func:`leaf_constraints_with` — a fit's own constraints by leaf name
  (``fit(..., bounds=, fixed=)``: :mod:`ceemx.identification.fitting.overrides`) over the
  classes' (:func:`ceemx.param`);
- :func:`label_at` and :func:`entry_labels` — the unit and description a :func:`ceemx.param`
  declares (the summary's unit column).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax.tree_util as jtu
import numpy as np

from ceemx.models.constraints import (
    CONSTRAINT_KEY,
    DESCRIPTION_KEY,
    UNIT_KEY,
    AbstractConstraint,
    child_of,
    leaf_constraints,
)

__all__ = ["Overrides", "entry_labels", "label_at", "leaf_constraints_with", "leaf_names"]

Overrides = tuple[tuple[str, AbstractConstraint], ...]
"""Per-fit constraints: ``(leaf name, constraint)`` pairs (:func:`leaf_constraints_with`)."""


def leaf_names(system: Any) -> list[str]:
    """The name of each leaf of ``system`` as written: ``k``, ``physics.k``, ``obs_noise.scale``."""
    paths = jtu.tree_flatten_with_path(system)[0]
    return [jtu.keystr(path).removeprefix(".") for path, _ in paths]


def leaf_constraints_with(system: Any, overrides: Overrides) -> list[AbstractConstraint]:
    """Each leaf's constraint: the class's (:func:`ceemx.param`), or the per-fit one of its name.

    ``overrides``: ``(name, constraint)`` pairs, names as :func:`leaf_names` writes them
    (``fit(..., bounds=..., fixed=...)``: :mod:`ceemx.identification.fitting.overrides`).
    """
    constraints = leaf_constraints(system)
    if not overrides:
        return constraints
    given = dict(overrides)
    return [given.get(n, c) for n, c in zip(leaf_names(system), constraints, strict=True)]


def label_at(tree: Any, path: tuple) -> tuple[str, str]:
    """``(unit, description)`` of the leaf at key ``path`` of ``tree`` (``""`` where none).

    From the :func:`param` of the outermost field above the leaf, as for its constraint.
    """
    node = tree
    for key in path:
        if isinstance(node, eqx.Module) and isinstance(key, jtu.GetAttrKey):
            meta = _field_metadata(node, key.name)
            if CONSTRAINT_KEY in meta:
                return meta.get(UNIT_KEY, ""), meta.get(DESCRIPTION_KEY, "")
        ok, node = child_of(node, key)
        if not ok:
            break
    return "", ""


def _field_metadata(module: Any, name: str) -> Any:
    if dataclasses.is_dataclass(module):
        for f in dataclasses.fields(module):
            if f.name == name:
                return f.metadata
    return {}


def entry_labels(template: Any, system: Any) -> list[tuple[str, str]]:
    """``(unit, description)`` per entry of a fit's θ, from ``system``'s fields.

    ``template``: the fit's trainable leaves (``None`` elsewhere); the labels are read off
    ``system``, whose classes declare them (the template, rebuilt by constraints, does not).
    """
    mask = jtu.tree_map(lambda v: v is not None, template, is_leaf=lambda v: v is None)
    params, _ = eqx.partition(system, mask)
    out: list[tuple[str, str]] = []
    for path, leaf in jtu.tree_flatten_with_path(params)[0]:
        out += [label_at(system, path)] * int(np.size(leaf))
    return out
