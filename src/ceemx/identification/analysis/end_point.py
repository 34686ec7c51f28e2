"""The end point of a fit as the analyses read it: problem, θ, states and weights."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from ceemx.identification.problem import FitProblem
from ceemx.lib.tree import as_jax

__all__ = ["end_point"]


def end_point(result: Any) -> tuple[FitProblem, Any, Any, Any]:
    """(problem, θ, states, weights) of the trajectories a :class:`ceemx.FitResult` fitted.

    The excluded trajectories (the start-of-fit health test) are left out; weights default to 1.

    Raises:
        ValueError: for a result built by hand (no problem: the analyses need :func:`ceemx.fit`).
    """
    if result.problem is None or result.theta is None:
        raise ValueError("This FitResult holds no problem: parameter uncertainty needs `fit`.")
    keep = np.setdiff1d(np.arange(result.states.shape[0]), np.asarray(result.excluded, int))
    states = result.states if not result.excluded else result.states[as_jax(keep)]
    weights = result.weights
    if weights is None:
        weights = jnp.ones(states.shape[0], states.dtype)
    return result.problem, result.theta, states, weights
