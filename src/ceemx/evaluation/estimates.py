"""Summaries over seeds: the mean and its standard error (:class:`Estimate`, :func:`mean_se`).

Shared by the metrics that produce the numbers (:mod:`ceemx.evaluation.metrics`) and the tables
that report them (:mod:`ceemx.evaluation.report`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Estimate", "mean_se"]


class Estimate(NamedTuple):
    """Mean and standard error (sample std, ddof=1, over √n, as the authors' tables) of n values."""

    mean: float
    se: float
    n: int

    def within(self, truth: float, k: float = 2.0) -> bool:
        """Whether |mean − truth| ≤ k·SE (the paper's Table 1 flags means outside 2 SE)."""
        return bool(abs(self.mean - truth) <= k * self.se)


def mean_se(values) -> Estimate:
    """:class:`Estimate` of a 1-D sample (SE = 0 for a single value)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("mean_se of an empty sample")
    se = float(np.std(v, ddof=1) / np.sqrt(v.size)) if v.size > 1 else 0.0
    return Estimate(float(np.mean(v)), se, int(v.size))
