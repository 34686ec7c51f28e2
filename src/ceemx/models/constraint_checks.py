"""Values against their declared constraints, checked on the host before any compute.

- :func:`check_constraints` — every leaf of a system inside its constraint
  (:mod:`ceemx.models.constraints`), the message naming the field;
- :func:`check_room` — a trainable start value not on its bound to within rounding (there the
  constraint's transform is saturated and a fit could never move it).

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

__all__ = ["ROOM_ULPS", "check_constraints", "check_room"]


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


def check_room(
    constraint: AbstractConstraint, x: Any, z: Any, where: str, *, back: Any = None
) -> None:
    """Refuse a trainable start value ``x`` that sits on its bound to within rounding.

    ``z`` is ``constraint.inverse(x)``, the unconstrained value a fit learns. Refused (host-side,
    before any compute; traced values are skipped): ``z`` not finite (``param(positive=True)``
    started at 1e-320 gives z = −inf: subnormals flush to zero); ``forward(z)`` not strictly
    inside (the start rounds onto its bound); ``x`` within :data:`ROOM_ULPS` units of rounding
    of a finite bound b, i.e. |x − b| ≤ 64·ε·|b| (or below the smallest normal number for
    b = 0) — ``upper=-2`` started at −2 − 4e-16, or ``lower=1, upper=5`` at 1 + 1e-15, where the
    transform is saturated: the representable values nearby are a few ulps apart, so no step can
    move the parameter and a fit stops at once, reporting success.

    ``back``: ``forward(z)`` when the caller has it already (computed here otherwise).

    Raises:
        ValueError: naming ``where`` (e.g. ``system.k``), the value, the bound and what to do.
    """
    if not (_is_concrete(x) and _is_concrete(z)):
        return
    xa, za = np.asarray(x), np.asarray(z)
    if not np.issubdtype(xa.dtype, np.floating):
        return
    finfo = np.finfo(xa.dtype)
    lower, upper = constraint.bounds
    with np.errstate(all="ignore"):
        bad = ~np.isfinite(za)
        back = np.asarray(constraint.forward(jnp.asarray(z)) if back is None else back)
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
