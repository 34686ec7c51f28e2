"""The smoothing step: MAP state trajectories (paper Eq. 10)."""

from .solver import (
    LMSmoother,
    SmootherSolution,
    check_inputs,
    promote_inputs,
    smooth,
    smooth_batch,
)

__all__ = [
    "LMSmoother",
    "SmootherSolution",
    "check_inputs",
    "promote_inputs",
    "smooth",
    "smooth_batch",
]
