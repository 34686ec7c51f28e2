"""How small a learned observation noise may be: the data's resolution and the evidence's margin.

The Laplace log-evidence that :func:`~ceemx.identification.analysis.noise_estimate.estimate_noise`
maximises has a degenerate boundary: as the observation noise σ_v → 0 the states interpolate the
data, the process noise carries every residual, and the evidence tends to a finite limit. Where
the record cannot tell observation noise from process noise acting on the observed states — a
θ still far from the optimum, whose model error the process noise absorbs, or a sensor much finer
than the process's one-step spread — the evidence rises, or stays flat, all the way down, and its
"maximum" is the lower edge of the search box (guess·e⁻¹²). A CE fit at that noise weighs each
sample as exact: the states follow the data, θ is fitted to one-step residuals, and the fit
converges in a few epochs to a model that free-runs far worse than one fitted at a loose noise.

Two floors, each from the data, and the estimate is the evidence maximum over σ_v at or above the
larger of them:

- **The resolution of y.** No record shows noise finer than its own resolution: where an output's
  present values lie on a grid — an encoder's or an ADC's quantum, the smallest nonzero
  difference between them, every other a whole multiple of it (:func:`output_resolution`) —
  σ_v is held at or above quantum/√12, the standard deviation of the rounding error.
  Continuous data lie on no grid and set no such floor.
- **The evidence's margin.** When the evidence at the box's lower edge is within
  :data:`EVIDENCE_MARGIN` nats of its maximum, or when the states at the maximum interpolate the
  data (the observation residuals' mean squared whitened value below 1e-4, the noise check's
  criterion), the data do not determine σ_v: they cannot reject σ_v → 0 and bound it from above
  only. σ_v is then the largest value whose evidence lies within the margin of the maximum — the
  upper end of its 95 % profile interval (1.92 nats: half the 95 % point of χ²₁), the loose side,
  which is the safe side for a CE fit. The second test finds a maximum far below the data's noise,
  where the states' Hessian barely resolves σ_v (σ_v ≈ 1e-8 against 0.01 on a Lorenz record whose
  process noise dominates): the evidence there is flat up to the true scale but dips and falls
  numerically toward the box's edge, so the first test misses it, and a Laplace finish at that σ_v
  loses every digit; its margin is searched from the box's upper edge down, past such dips, and
  measured from the best evidence on the decades above the maximum (:func:`plateau`): the
  maximum's own value can be a numerical spike above the evidence's limit as σ_v → 0. Where
  the evidence is flat over the whole box the observation noise is not determined by the data at all
  and the estimate says so (:attr:`NoiseMoments.notes`).

Where a record holds no observation, or every observed output is constant, no noise can be told
from signal and the estimate is refused (:func:`check_informative`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from ceemx.data.trajectories import Trajectories
from ceemx.identification.analysis.evidence_search import DECADE, EvidenceSearch

__all__ = [
    "EVIDENCE_MARGIN",
    "check_informative",
    "flagged",
    "margin_floor",
    "output_resolution",
    "plateau",
    "resolution_floor",
    "top_margin",
    "with_floors",
]

#: nats below the evidence's maximum that bound a degenerate observation noise from above (half
#: the 95 % point of χ²₁: the upper end of the 95 % profile-likelihood interval)
EVIDENCE_MARGIN = 1.92

#: bisection steps of :func:`margin_floor` (a decade bracket to 1/64 of a decade)
_BISECTIONS = 6

#: how far from a whole multiple of the smallest gap every gap may lie on a quantised output
_ON_GRID = 1e-3

#: values of one output closer than this many units in the last place of its largest magnitude
#: are the same value (data written as decimals and read back differ there, not in the quantum)
_SAME_ULPS = 64


def output_resolution(data: Trajectories) -> np.ndarray:
    """(m,) per output, the quantum its present values lie on (NaN: none).

    The smallest nonzero difference between the values, when every difference is a whole
    multiple of it (to 1e-3): an encoder's or an ADC's step. Continuous data lie on no grid
    (their smallest gap, about range / N², says nothing of their noise): NaN. Differences
    within ``64·eps·max|y|`` count as equal values (rounding of the stored numbers).
    """
    y = np.asarray(data.y, np.float64)
    mask = np.asarray(data.mask, bool)
    out = np.full(y.shape[-1], np.nan)
    for i in range(y.shape[-1]):
        gaps = _gaps(y[..., i][mask[..., i]])
        if gaps.size:
            step = float(gaps.min())
            multiples = gaps / step
            if np.all(np.abs(multiples - np.round(multiples)) <= _ON_GRID):
                out[i] = step
    return out


def _gaps(values: np.ndarray) -> np.ndarray:
    """The nonzero differences between consecutive distinct values."""
    values = np.unique(values)
    if values.size < 2:
        return np.zeros(0)
    gaps = np.diff(values)
    return gaps[gaps > _SAME_ULPS * np.finfo(np.float64).eps * np.max(np.abs(values))]


def resolution_floor(data: Trajectories) -> np.ndarray:
    """(m,) the smallest noise std a quantised output can show: quantum / √12 (NaN: no grid).

    The standard deviation of the rounding error.
    """
    return output_resolution(data) / np.sqrt(12.0)


def check_informative(data: Trajectories) -> None:
    """Refuse a record from which no noise can be learned.

    Raises:
        ValueError: every observation is masked, or every observed output is constant.
    """
    y = np.asarray(data.y, np.float64)
    mask = np.asarray(data.mask, bool)
    if not mask.any():
        raise ValueError(
            "the data hold no observation (every y is masked): there is nothing to learn the "
            "noise from. Fit at a given noise (noise='fixed'), or pass data with observations."
        )
    if not any(_gaps(y[..., i][mask[..., i]]).size for i in range(y.shape[-1])):
        raise ValueError(
            "every observed output is constant: the data show no variation from which noise could "
            "be told from signal (the evidence would rise without bound as the noise shrinks). "
            "Fit at a given noise (noise='fixed')."
        )


def margin_floor(
    objective: Callable[[float], float], z_best: float, f_best: float, upper: float, step: float
) -> tuple[float, bool]:
    """The largest log-scale z ≥ ``z_best`` with ``objective(z) ≤ f_best + EVIDENCE_MARGIN``.

    Args:
        objective: −(log-evidence) as a function of the one log-scale (the others held).
        z_best: where it is smallest (at or near the box's lower edge).
        f_best: its value there.
        upper: the box's upper edge.
        step: the step of the bracketing search (a decade).

    Returns:
        ``(z, determined)``: the upper end of the margin, to 1/64 of ``step``; ``determined`` is
        ``False`` when the evidence stays within the margin up to the box's upper edge (``z`` is
        that edge).
    """
    level = f_best + EVIDENCE_MARGIN
    below, above = z_best, None
    while above is None:
        z = min(below + step, upper)
        if not objective(z) <= level:
            above = z
        elif z >= upper:
            return upper, False
        else:
            below = z
    return _bisect(objective, level, below, above), True


def top_margin(
    objective: Callable[[float], float], z_best: float, f_best: float, upper: float, step: float
) -> tuple[float, bool]:
    """:func:`margin_floor`'s answer, searched from ``upper`` down.

    The largest log-scale z ≥ ``z_best`` with ``objective(z) ≤ f_best + EVIDENCE_MARGIN``.
    :func:`margin_floor` climbs from the maximum and stops at the first point outside the
    margin; at a maximum where the states interpolate the data the evidence can dip there
    numerically and rise again toward the data's noise, which this search, coming down from the
    box's edge a ``step`` at a time, does not stop at.

    Returns:
        ``(z, determined)``: the upper end to 1/64 of ``step``; ``determined`` is ``False`` when
        the evidence is within the margin at ``upper`` itself (``z`` is that edge). ``z_best``
        itself when no point above it is within the margin.
    """
    level = f_best + EVIDENCE_MARGIN
    above, z = None, upper
    while z > z_best:
        if objective(z) <= level:
            break
        above, z = z, z - step
    else:
        return z_best, True
    if above is None:
        return upper, False
    below = z
    return _bisect(objective, level, below, above), True


def plateau(
    objective: Callable[[float], float], z_best: float, f_best: float, upper: float, step: float
) -> float:
    """The reference value of a margin from a maximum where the states interpolate the data.

    The best ``objective`` (−evidence) above ``z_best`` on :func:`top_margin`'s points
    (``upper``, ``upper − step``, ...; the search then finds them evaluated), not at ``z_best``
    itself: there the states' Hessian has lost most of its digits and the evidence can spike
    above its limit as σ_v → 0 (a Lorenz record: 93.7 nats at σ_v = 3.6e-9 between 90.9 one
    decade above and −28 one below, over a plateau at 90.96 up to 3.6e-3) — a margin measured
    from the spike holds σ_v at the spike. ``f_best`` when no point lies above it.
    """
    values, z = [], upper
    while z > z_best:
        values.append(objective(z))
        z -= step
    return min(values, default=f_best)


def _bisect(objective: Callable[[float], float], level: float, below: float, above: float) -> float:
    """The margin's end between ``below`` (within it) and ``above`` (outside it), to 1/64."""
    for _ in range(_BISECTIONS):
        mid = 0.5 * (below + above)
        if objective(mid) <= level:
            below = mid
        else:
            above = mid
    return below


def with_floors(
    search: EvidenceSearch, layout: Any, data: Trajectories, interpolates: bool = False
) -> EvidenceSearch:
    """The search re-run with each observation scale bounded below by its floors (module notes).

    The resolution floor of a quantised output always; the evidence's margin where the evidence
    at the box's lower edge (the other scales at the best point) is within
    :data:`EVIDENCE_MARGIN` of its maximum, or where the states at the maximum interpolate the
    data (``interpolates``, from the caller: the noise check's criterion) — the margin's upper
    end then searched from the box's upper edge down (:func:`top_margin`).
    ``search`` itself when no floor lies above its estimate; else a search that shares its
    evaluations, its ``floors`` recording each raised bound and why.

    Args:
        search: the finished search.
        layout: the estimate's scale layout (``entries_of``, ``floor_z``).
        data: the record (its resolution).
        interpolates: whether the MAP states at the maximum interpolate the data.
    """
    z_star, floors = search.best_z, {}
    resolution = resolution_floor(data)
    for i in layout.entries_of("obs_noise"):
        lo, hi = search.bounds[i]

        def along(zi, i=i):
            z = z_star.copy()
            z[i] = zi
            return search.objective(z)[0]

        z_floor, why = layout.floor_z(i, resolution), "resolution"
        f_star, f_edge = along(z_star[i]), along(lo)
        z_margin, determined = None, True
        if f_edge <= f_star + EVIDENCE_MARGIN:  # the data cannot reject σ_v → 0
            f_min = min(f_star, f_edge)
            start = float(z_star[i]) if f_star <= f_min + EVIDENCE_MARGIN else lo
            z_margin, determined = margin_floor(along, start, f_min, hi, DECADE)
        elif interpolates:  # a maximum where the states interpolate the data
            f_ref = plateau(along, float(z_star[i]), f_star, hi, DECADE)
            z_margin, determined = top_margin(along, float(z_star[i]), f_ref, hi, DECADE)
        if z_margin is not None and z_margin > z_floor:
            z_floor, why = z_margin, "margin" if determined else "flat"
        z_floor = min(z_floor, hi)
        if z_floor > z_star[i]:
            floors[i] = (z_floor, why)
    return search.floored(floors) if floors else search


def flagged(nm, layout: Any, stds: dict[str, np.ndarray], z: np.ndarray, search: EvidenceSearch):
    """``nm`` with the fields held at a floor or sitting at an edge of the box named, and why.

    Args:
        nm: the moments at the estimate.
        layout: the estimate's scale layout (``entry_fields``).
        stds: the estimate's standard deviations per noise field.
        z: the estimate's log-scales.
        search: the search that found it (``floors``, ``box``).
    """
    floored, degenerate, at_edge, notes = [], [], [], []
    for i, field in enumerate(layout.entry_fields):
        z_floor, why = search.floors.get(i, (None, ""))
        lo, hi = search.box[i]
        std = ", ".join(f"{v:.3g}" for v in np.atleast_1d(stds[field]))
        if z_floor is not None and z[i] <= z_floor + _EDGE:
            floored.append(field)
            if why != "resolution":
                degenerate.append(field)
            notes.append(_FLOOR_NOTES[why].format(field=field, std=std))
        if z[i] <= lo + _EDGE or z[i] >= hi - _EDGE:
            at_edge.append(field)
            way = "lower" if z[i] <= lo + _EDGE else "upper"
            notes.append(_EDGE_NOTE.format(field=field, way=way, std=std))
    return dataclasses.replace(
        nm,
        floored=tuple(dict.fromkeys(floored)),
        degenerate=tuple(dict.fromkeys(degenerate)),
        at_edge=tuple(dict.fromkeys(at_edge)),
        notes=tuple(notes),
    )


#: how close (in log-scale) to a bound an estimate counts as sitting on it
_EDGE = 1e-3

_FLOOR_NOTES = {
    "resolution": "{field}: held at std {std}, the quantum of y / √12 (its values lie on a "
    "grid): the evidence's maximum lies below what the record can show",
    "margin": "{field}: held at std {std}, the largest the data allow (evidence within "
    f"{EVIDENCE_MARGIN} nats of its maximum): the evidence does not fall as the observation "
    "noise → 0, where the states would interpolate the data",
    "flat": "{field}: the evidence is flat over the whole search box, the data do not determine "
    "it; held at std {std}, the box's upper edge",
}
_EDGE_NOTE = (
    "{field}: the estimate (std {std}) sits at the {way} edge of its search box (the start's "
    "scale times e^±12, moved beyond it where the data's scale lay there): the evidence keeps "
    "rising beyond it — the data's scale far from the guess, or a scale the data do not "
    "determine"
)
