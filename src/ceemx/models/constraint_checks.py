"""Values against their declared constraints, checked on the host before any compute.

- :func:`check_constraints` — every leaf of a system inside its constraint
  (:mod:`ceemx.models.constraints`), the message naming the field;
- :func:`check_room` — a trainable start value not on its bound to within rounding (there the
  constraint's transform is saturated and a fit could never move it), nor at a scale no fit can
  start from (:data:`ABSURD_MAGNITUDE`, :data:`RELATIVE_NEARNESS`, :data:`ABSURD_NEARNESS`).

Traced values (inside ``jit``) are skipped.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.core import Tracer

from ceemx.models.constraints import AbstractConstraint, Fixed, Unconstrained, constraint_at

__all__ = [
    "ABSURD_MAGNITUDE",
    "ABSURD_NEARNESS",
    "RELATIVE_NEARNESS",
    "ROOM_ULPS",
    "check_constraints",
    "check_room",
]


def _is_concrete(leaf: Any) -> bool:
    return eqx.is_array_like(leaf) and not isinstance(leaf, Tracer)


def check_constraints(tree: Any, name: str = "system") -> None:
    """Raise ``ValueError`` naming the field when a leaf lies outside its declared constraint.

    Host-side; traced leaves (inside ``jit``) are skipped. The message reads e.g.
    "`system.k1` must be > 0 (positive); got -0.3." (``name`` is its first word).
    """
    pairs, _ = jtu.tree_flatten_with_path(tree)
    for path, leaf in pairs:
        c = constraint_at(tree, path)
        if isinstance(c, Unconstrained | Fixed) or not _is_concrete(leaf):
            continue
        value = np.asarray(leaf)
        inside = np.asarray(c.contains(value), bool)
        if not np.all(inside):
            where = f"{name}{jtu.keystr(path)}"
            if value.ndim == 0:
                got = f"got {value.item()!r}"
            else:
                idx = tuple(int(i) for i in np.argwhere(~inside)[0])
                got = f"entry {idx} is {value[idx].item()!r}"
            raise ValueError(f"`{where}` must be {c.description}; {got}.")


#: A trainable value within this many units of rounding (of its bound's size) of a bound is
#: refused at the start of a fit (:func:`check_room`).
ROOM_ULPS = 64

#: A trainable start value of this magnitude or more is refused (:func:`check_room`).
ABSURD_MAGNITUDE = 1e100
#: A trainable start value nearer than this fraction of its bound's scale to the bound is refused:
#: the scale is an interval's width, or |b| for a one-sided bound b ≠ 0.
RELATIVE_NEARNESS = 1e-10
#: A trainable start value nearer than this to a bound at 0 (no scale of its own) is refused.
ABSURD_NEARNESS = 1e-100


def check_room(
    constraint: AbstractConstraint, x: Any, z: Any, where: str, *, back: Any = None
) -> None:
    """Refuse a trainable start value ``x`` that sits on its bound, or at an absurd scale.

    ``z`` is ``constraint.inverse(x)``, the unconstrained value a fit learns. Refused (host-side,
    before any compute; traced values are skipped): ``z`` not finite (``param(positive=True)``
    started at 1e-320 gives z = −inf: subnormals flush to zero); ``forward(z)`` not strictly
    inside (the start rounds onto its bound); ``x`` within :data:`ROOM_ULPS` units of rounding
    of a finite bound b, i.e. |x − b| ≤ 64·ε·|b| (or below the smallest normal number for
    b = 0) — ``upper=-2`` started at −2 − 4e-16, or ``lower=1, upper=5`` at 1 + 1e-15, where the
    transform is saturated: the representable values nearby are a few ulps apart, so no step can
    move the parameter and a fit stops at once, reporting success. Then the scales no fit can
    start from (:func:`_check_scale`): |x| ≥ 1e100; within 1e-10 of the bound's scale of a bound
    (an interval's width, |b| for a one-sided b ≠ 0); within 1e-100 of a bound at 0.

    ``back``: ``forward(z)`` when the caller has it already (computed here otherwise).

    Raises:
        ValueError: naming ``where`` (e.g. ``system.k``), the value, the bound and what to do.
    """
    if not (_is_concrete(x) and _is_concrete(z)):
        return
    xa, za = np.asarray(x), np.asarray(z)
    if not np.issubdtype(xa.dtype, np.floating):
        return
    _check_rounding(constraint, xa, za, where, back)
    _check_scale(constraint, xa, za, where)


def _check_rounding(constraint: AbstractConstraint, xa, za, where: str, back) -> None:
    """:func:`check_room`'s refusal of a value on its bound to within rounding."""
    finfo = np.finfo(xa.dtype)
    lower, upper = constraint.bounds
    with np.errstate(all="ignore"):
        bad = ~np.isfinite(za)
        back = np.asarray(constraint.forward(jnp.asarray(za)) if back is None else back)
        bad |= ~np.asarray(constraint.contains(back), bool)
        for b in (lower, upper):
            if math.isfinite(b):
                bad |= np.abs(xa - b) <= max(ROOM_ULPS * float(finfo.eps) * abs(b), finfo.tiny)
    if not np.any(bad):
        return
    idx = tuple(int(i) for i in np.argwhere(bad)[0]) if xa.ndim else ()
    value = xa[idx].item()
    entry = f" entry {idx}" if xa.ndim else ""
    raise ValueError(
        f"`{where}`{entry} = {value!r} is within rounding of its bound (it must be "
        f"{constraint.description}): in the unconstrained coordinates a fit learns it is "
        f"{za[idx].item():.4g}, where the constraint's transform is saturated (or infinite), so "
        "the parameter could never move. Start it further inside the allowed set (more than "
        f"{ROOM_ULPS} units of rounding from the bound), or fix it (`ceemx.param(fixed=True)` "
        "or leave it out of `trainable`)."
    )


def _nearness(lower: float, upper: float, b: float) -> float:
    """The distance to bound ``b`` below which :func:`_check_scale` refuses a start."""
    if math.isfinite(lower) and math.isfinite(upper):
        return RELATIVE_NEARNESS * (upper - lower)
    return RELATIVE_NEARNESS * abs(b) if b != 0 else ABSURD_NEARNESS


def _check_scale(constraint: AbstractConstraint, xa, za, where: str) -> None:
    """:func:`check_room`'s refusal of a start at a scale no fit can move from.

    Refused: |x| ≥ :data:`ABSURD_MAGNITUDE` (1e100); a distance d to a bound below
    :data:`RELATIVE_NEARNESS` (1e-10) of the bound's scale — an interval's width, |b| for a
    one-sided bound b ≠ 0 (the value agrees with its bound to ten digits) — or below
    :data:`ABSURD_NEARNESS` (1e-100) for a bound at 0, which has no scale of its own. No
    quantity in any system of units is that large, or that close to where its model stops being
    defined; such a start is a unit error or an uninitialised value. Near a bound the transform's
    slope dx/dz is ≈ d: every derivative of J in the unconstrained coordinate carries that factor
    and the parameter's Gauss–Newton curvature d², which Marquardt's scaling treats as zero
    beside the others' (below 1e-10 of the largest), so no step moves it and the fit stops where
    it started, "converged" (``param(positive=True)`` at 1e-300, ``param(lower=1, upper=5)`` at
    1 + 1e-12). At 1e100 the states absorb the scale (the model's outputs unchanged, J flat in
    θ).
    """
    lower, upper = constraint.bounds
    with np.errstate(all="ignore"):
        big = np.isfinite(xa) & (np.abs(xa) >= ABSURD_MAGNITUDE)
        near = np.zeros(xa.shape, bool)
        for b in (lower, upper):
            if math.isfinite(b):
                near |= np.abs(xa - b) < _nearness(lower, upper, b)
    bad = big | near
    if not np.any(bad):
        return
    idx = tuple(int(i) for i in np.argwhere(bad)[0]) if xa.ndim else ()
    value = xa[idx].item()
    entry = f" entry {idx}" if xa.ndim else ""
    name = f"`{where}`{entry} = {value!r}"
    if big[idx]:
        raise ValueError(
            f"{name} is {ABSURD_MAGNITUDE:.0e} or more in magnitude: no quantity in any "
            "system of units is that large, so it is a unit error or an uninitialised value. "
            "At that scale the states absorb it (the model's outputs do not change with it) and "
            "its squares and products in the fit overflow; the fit could not move it. Start it "
            "at a value of the size the data suggest."
        )
    b = lower if abs(value - lower) <= abs(value - upper) else upper
    limit = f"{_nearness(lower, upper, b):.3g}"
    raise ValueError(
        f"{name} is {abs(value - b):.3g} from its bound {b:g} (it must be "
        f"{constraint.description}; a start nearer than {limit} is refused): there the "
        "constraint's transform has a slope of about that distance, so J hardly depends on the "
        f"parameter's unconstrained value ({za[idx].item():.4g}), no step can move it and the "
        "fit would stop where it started. Start it at a value of the size the data suggest, or "
        "fix it (`ceemx.param(fixed=True)` or leave it out of `trainable`)."
    )
