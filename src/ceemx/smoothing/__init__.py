"""The smoothing step: MAP state trajectories."""

from .solver import RESULTS, LMSmoother, SmootherSolution, check_inputs, smooth

__all__ = ["RESULTS", "LMSmoother", "SmootherSolution", "check_inputs", "smooth"]
