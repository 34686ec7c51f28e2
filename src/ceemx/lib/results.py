"""Status codes of ceemx's iterative solvers, as an :class:`equinox.Enumeration`.

Batched solves (a smoother over B trajectories) return one status per element: an
``EnumerationItem`` whose value has a batch axis. Compare with ``==`` (``status ==
RESULTS.successful`` is a boolean array); :func:`codes` and :func:`messages` read them on the host.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool

__all__ = ["RESULTS", "codes", "from_codes", "messages", "select"]


class RESULTS(eqx.Enumeration):
    """Outcome of an iterative solve (per trajectory for batched solves)."""

    successful = "converged"
    max_steps_reached = "reached max_steps before converging"
    nonfinite = "the objective or its derivatives are not finite at the initial point"
    stalled = "no step decreases the objective (damping exhausted) before the tolerances were met"
    particle_failure = (
        "the particle filter's likelihood estimate is not finite (every particle impossible, or "
        "a non-finite model value)"
    )
    outlier = (
        "excluded from the fit: its residuals at the start are far outside the noise model, "
        "compared with the other trajectories (ceemx.identification.fitting.health)"
    )
    diverged = (
        "the free-run simulation is not finite: the model diverges (or overflows) from its "
        "initial state under these inputs"
    )
    never_moved = (
        "not converged: the fit never moved (θ, or the states while θ moved, the same as at the "
        "start after every epoch): every step was refused or rounded away, so the stopping rule "
        "was met without a fit (non-finite model values wherever the steps led, a model that "
        "does not depend on what is learned)"
    )
    nonfinite_objective = (
        "not converged: the objective (J, or the method's own) or its derivatives became "
        "non-finite during the fit, from a finite start"
    )
    constant_output = (
        "a scored test output is constant (one value): its NRMSE and fit % (relative to the "
        "output's spread) are undefined, NaN; the RMSE stands"
    )


def codes(status: RESULTS) -> np.ndarray:
    """The integer codes of a (possibly batched) status, on the host."""
    return np.asarray(status._value)  # the one place that reads the item's raw value


def from_codes(values: ArrayLike) -> RESULTS:
    """A status item from integer codes (e.g. read back from a checkpoint or history)."""
    values = jnp.asarray(values, jnp.int32)
    out = RESULTS.successful
    for index, item in enumerate(_ITEMS):
        out = select(values == index, item, out)
    return out


def select(pred: Bool[ArrayLike, ...], a: RESULTS, b: RESULTS) -> RESULTS:
    """``RESULTS.where`` for a predicate of any shape (elementwise; broadcast items)."""
    pred = jnp.asarray(pred)
    if pred.ndim == 0:
        return RESULTS.where(pred, a, b)
    return _select(pred, a, b)


@eqx.filter_jit  # compiled once per shape: eagerly, the vmap below was traced at every call
def _select(pred: Bool[Array, ...], a: RESULTS, b: RESULTS) -> RESULTS:
    flat = pred.reshape(-1)
    a_b = jax.tree_util.tree_map(lambda v: jnp.broadcast_to(v, pred.shape).reshape(-1), a)
    b_b = jax.tree_util.tree_map(lambda v: jnp.broadcast_to(v, pred.shape).reshape(-1), b)
    out = jax.vmap(RESULTS.where)(flat, a_b, b_b)
    return jax.tree_util.tree_map(lambda v: v.reshape(pred.shape), out)


def messages(status: RESULTS) -> list[str]:
    """One human-readable message per element of a (possibly batched) status."""
    return [RESULTS[from_codes(c)] for c in np.atleast_1d(codes(status)).reshape(-1)]


_ITEMS = (
    RESULTS.successful,
    RESULTS.max_steps_reached,
    RESULTS.nonfinite,
    RESULTS.stalled,
    RESULTS.particle_failure,
    RESULTS.outlier,
    RESULTS.diverged,
    RESULTS.never_moved,
    RESULTS.nonfinite_objective,
    RESULTS.constant_output,
)
