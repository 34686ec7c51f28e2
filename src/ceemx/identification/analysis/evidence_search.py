"""The search of ``estimate_noise``: the Laplace log-evidence over log-scales z, in a box.

:func:`~ceemx.identification.analysis.noise_estimate.estimate_noise` searches by a grid of
decades, L-BFGS and decade steps.

What one evaluation is (a MAP smoothing and its posterior at the noise z sets) and its gradient
are given by the caller; this module holds the search: :class:`EvidenceSearch` (cached
evaluations, the best point inside the bounds, L-BFGS-B, the decade steps that leave a flat
evidence, the same search with some lower bounds raised) and :func:`decade_grid`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["DECADE", "EDGE", "LOG_RANGE", "EvidenceSearch", "decade_grid", "moved"]

#: how far (in log-scale) from its start a scale may move in one estimate: a factor e^12 ≈ 1.6e5
LOG_RANGE = 12.0
#: one decade in log-scale
DECADE = float(np.log(10.0))
#: restarts of L-BFGS from a decade step that found more evidence
_ESCAPES = 3
#: how close (in log-scale) to an edge of the box a best point sits *at* it
EDGE = 1e-6


class EvidenceSearch:
    """−(Laplace log-evidence) of one data set in the log-scales z, its gradient, its best point.

    Each evaluation smooths from the best point's MAP states so far (warm), and is cached.

    Args:
        evaluate: ``(z, start states) -> moments`` (with ``.evidence`` and ``.states``).
        gradient: ``(z, moments) -> ∂ log-evidence / ∂z``.
        z0: the start, evaluated as ``nm``.
        nm: the moments at ``z0``.
        bounds: (lo, hi) per entry of z: the search box.
        max_evaluations: bound on the evaluations of one L-BFGS run.
    """

    def __init__(
        self,
        evaluate: Callable[[np.ndarray, Any], Any],
        gradient: Callable[[np.ndarray, Any], np.ndarray],
        z0: np.ndarray,
        nm,
        bounds: list[tuple[float, float]],
        max_evaluations: int,
    ):
        self.evaluate, self.gradient = evaluate, gradient
        self.bounds, self.max_evaluations = list(bounds), max_evaluations
        #: the search box (``bounds`` before any floor), and the raised lower bounds: index →
        #: (z, why) (:meth:`floored`)
        self.box, self.floors = list(bounds), {}
        # |∂/∂ log σ| at which to stop: the evidence's curvature in a log-scale is ≈ 2N (N
        # residuals), so the gain still ahead, ≈ g²/4N, is then 1e-8 nat from N = 2 500 on
        # (the fixed 1e-2 of before below that, where it is ≤ 1e-5/N)
        self.steps = float(np.prod(nm.states.shape[:2]))
        self.gtol = 1e-2 * max(1.0, np.sqrt(self.steps / 2500.0))
        self.cache: dict[bytes, Any] = {z0.tobytes(): nm}
        self.best = {"f": -nm.evidence, "z": z0.copy(), "nm": nm}

    @property
    def best_z(self) -> np.ndarray:
        """A copy of the best z so far."""
        return self.best["z"].copy()

    def feasible(self, z: np.ndarray) -> bool:
        """Whether z lies inside the bounds."""
        return all(lo <= v <= hi for v, (lo, hi) in zip(z, self.bounds, strict=True))

    def objective(self, z):
        """(−evidence, its gradient in z) at z; 1e300 where the posterior is not finite."""
        key = z.tobytes()
        if key not in self.cache:
            self.cache[key] = self.evaluate(z, self.best["nm"].states)
        m = self.cache[key]
        f = -m.evidence
        if not np.isfinite(f):
            return 1e300, np.zeros_like(z)
        if f < self.best["f"] and self.feasible(z):
            self.best.update(f=f, z=z.copy(), nm=m)
        return f, -self.gradient(z, m)

    def refine(self, z):
        """L-BFGS-B from z (SciPy, on the host), on the evidence per time step.

        Per time step, so that its first step (the gradient's length) is of the scales' order
        whatever the data's size; summed, it jumped to the bounds on a 10⁵-sample record.
        """
        from scipy.optimize import minimize

        def scaled(z):
            f, g = self.objective(z)
            return f / self.steps, g / self.steps

        minimize(
            scaled,
            z,
            jac=True,
            method="L-BFGS-B",
            bounds=self.bounds,
            options={
                "maxfun": self.max_evaluations,
                "ftol": 1e-10,
                "gtol": self.gtol / self.steps,
            },
        )

    def climb(self, z):
        """L-BFGS from z, then from any decade step of one scale that gains (a few times).

        L-BFGS stops where the evidence goes flat: a scale → 0 (all the noise in the other
        model: a whole output-error plateau) or → ∞. A decade either way of each scale from
        its answer finds the slope again where it lies beyond (a 10⁵-sample record: σ_w stuck
        at 3e-6, 300× below the evidence's maximum, 2 400 nats lower).
        """
        self.refine(z)
        for _ in range(_ESCAPES):
            f_before, z_best = self.best["f"], self.best_z
            for k in range(z_best.size):
                for step in (DECADE, -DECADE):
                    z = z_best.copy()
                    z[k] += step
                    if self.bounds[k][0] <= z[k] <= self.bounds[k][1]:
                        self.objective(z)
            if not self.best["f"] < f_before - 1e-9 * abs(f_before):
                return
            self.refine(self.best_z)

    def floored(self, floors: dict[int, tuple[float, str]]) -> EvidenceSearch:
        """The search with the lower bounds of ``floors`` (index → (z, why)) raised, climbed.

        It shares this search's evaluations; it starts from the best of them inside the new
        bounds, or from the best point moved onto the floors.
        """
        out = copy.copy(self)
        out.floors = dict(floors)
        out.bounds = [
            (max(lo, floors[i][0]), hi) if i in floors else (lo, hi)
            for i, (lo, hi) in enumerate(self.box)
        ]
        start = np.clip(self.best_z, *np.array(out.bounds).T)
        out.best = {"f": np.inf, "z": start, "nm": self.best["nm"]}
        for key, m in self.cache.items():  # the best evaluation so far inside the new bounds
            z = np.frombuffer(key, np.float64)
            if out.feasible(z) and -m.evidence < out.best["f"]:
                out.best = {"f": -m.evidence, "z": z.copy(), "nm": m}
        out.objective(start)
        out.climb(out.best_z)
        return out


def moved(search: EvidenceSearch) -> EvidenceSearch | None:
    """The search with its box moved by :data:`LOG_RANGE` where the data's scale lies beyond it.

    Raised above every scale whose best sits at its upper edge: the evidence falls as a scale →
    ∞ (the posterior's volume is paid for in the log-determinant and the misfit is spread
    thinner), so a best there is never its maximum — the data's scale lies above the guess's box
    (data in μm, noise guessed in m). Lowered only where every scale sits at its lower edge: one
    scale there can be a real, flat limit (σ_v → 0 with the process noise carrying the
    residuals, analysis.noise_floor; σ_w → 0 on a deterministic record), every scale at once is
    the data's scale below the box. Climbed from the best so far; ``None`` where neither holds.
    """
    z = search.best_z
    up = [LOG_RANGE if z[i] >= hi - EDGE else 0.0 for i, (_, hi) in enumerate(search.box)]
    down = LOG_RANGE if all(z[i] <= lo + EDGE for i, (lo, _) in enumerate(search.box)) else 0.0
    if not any(up) and not down:
        return None
    out = copy.copy(search)
    out.box = [(lo - down, hi + d) for (lo, hi), d in zip(out.box, up, strict=True)]
    out.bounds = [(lo - down, hi + d) for (lo, hi), d in zip(out.bounds, up, strict=True)]
    out.best = dict(search.best)
    out.climb(out.best_z)
    return out


def decade_grid(z0: np.ndarray, decades: int = 3) -> list[np.ndarray]:
    """Points in decades of every factor (all combinations up to two factors, else one by one).

    ``decades`` either way of ``z0``: 7 points per factor by default, 3 for ``decades=1``.
    """
    steps = DECADE * np.arange(-float(decades), decades + 1.0)
    if z0.size <= 2:
        mesh = np.meshgrid(*[z + steps for z in z0], indexing="ij")
        return [np.array(p) for p in zip(*(m.ravel() for m in mesh), strict=True)]
    out = []
    for i in range(z0.size):
        for s in steps:
            z = z0.copy()
            z[i] += s
            out.append(z)
    return out
