"""When a fit of a model with a learned term may report converged: the term stopped improving.

The solvers' stopping rules judge one epoch: J rose by at most ``rtol·|J + c|``, or the joint
method's model predicts no decrease, or θ moves only along directions the data do not determine.
Those rules are sized for a few physical parameters. A learned term's weights move J a little per
epoch for many epochs, a stochastic learner's single epoch says little, and a network's weights
are never determined by the data (its symmetries, and the weight-decay prior pulling them toward
zero); so on a hybrid they stop the training while the term still changes ("converged after 5
epochs" with the term unmoved from zero).

A fit whose model has a learned term (:func:`has_learned_term`) therefore reports converged only
when, over the last :data:`TERM_WINDOW` epochs, J rose in all by at most the solver's one-epoch
tolerance and the term's weights moved by at most :data:`TERM_RTOL` of their norm
(:class:`TermProgress`). Until then a solver's "converged" does not stop the fit (other reasons to
stop — a stuck solver, a callback, ``max_epochs`` — still do, reported not converged). The
identifiability stop and end-point analysis do not apply to such models
(:mod:`ceemx.identification.analysis.identifiability`).
"""

from __future__ import annotations

from collections import deque
from typing import Any

import equinox as eqx
import jax.tree_util as jtu
import numpy as np

from ceemx.infra.distributed import to_host

__all__ = ["TERM_RTOL", "TERM_WINDOW", "TermProgress", "has_learned_term", "term_weights"]

#: Epochs over which a learned term must have stopped improving.
TERM_WINDOW = 5
#: The weights' change over the window, relative to their norm, below which the term settled.
TERM_RTOL = 1e-3


def _terms(system: Any) -> list:
    return [
        t
        for t in (getattr(system, "dynamics_term", None), getattr(system, "observation_term", None))
        if t is not None
    ]


def has_learned_term(system: Any) -> bool:
    """Whether ``system`` carries a learned term (a :mod:`ceemx.systems.hybrid` model's)."""
    return bool(_terms(system))


def term_weights(system: Any) -> np.ndarray | None:
    """The learned terms' weights, flattened (``None``: no learned term)."""
    terms = _terms(system)
    if not terms:
        return None
    leaves = jtu.tree_leaves(eqx.filter([t.net for t in terms], eqx.is_inexact_array))
    if not leaves:
        return None
    return np.concatenate([np.ravel(np.asarray(to_host(leaf), dtype=float)) for leaf in leaves])


def settled(J: list[float], weights: list[np.ndarray], tolerance: float) -> bool:
    """Whether the window (J and the weights at its ``TERM_WINDOW + 1`` ends) shows no progress.

    ``J[0]``, ``weights[0]``: the epoch before the window; ``tolerance``: the solver's one-epoch
    tolerance on J's rise.
    """
    if len(J) < TERM_WINDOW + 1 or not np.isfinite(J[-1]):
        return False
    rise = J[-1] - J[0]
    moved = float(np.linalg.norm(weights[-1] - weights[0]))
    size = float(np.linalg.norm(weights[-1]))
    return bool(rise <= tolerance and moved <= TERM_RTOL * size + 1e-12 * np.sqrt(size + 1.0))


class TermProgress:
    """The learned term's progress over the last :data:`TERM_WINDOW` epochs of one fit."""

    def __init__(self, J0: float, weights0: np.ndarray):
        """Start the window at the fit's start (its J and the term's weights)."""
        self.J: deque[float] = deque([float(J0)], maxlen=TERM_WINDOW + 1)
        self.weights: deque[np.ndarray] = deque([weights0], maxlen=TERM_WINDOW + 1)

    @classmethod
    def of(cls, system: Any, J0: float) -> TermProgress | None:
        """The tracker of a fit starting at ``system`` (``None``: no learned term)."""
        w = term_weights(system)
        return None if w is None else cls(J0, w)

    def update(self, system: Any, J: float, tolerance: float) -> bool:
        """Record an epoch's end (its system and J); whether the term settled over the window."""
        w = term_weights(system)
        self.J.append(float(J))
        self.weights.append(self.weights[-1] if w is None else w)
        return settled(list(self.J), list(self.weights), tolerance)
