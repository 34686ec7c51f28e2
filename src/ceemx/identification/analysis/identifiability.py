"""Identifiability: which parameter combinations the data determine, named as the user wrote them.

The Gauss–Newton curvature of −J in θ with the states eliminated is the Schur complement
S = D − Σ_b E_bᵀ A_b⁻¹ E_b of the joint (x, θ) system (:func:`ceemx.identification.schur.
schur_complement`; its inverse is the Laplace covariance of θ). A direction of θ along which S is
(near) zero is one the data do not determine: J is flat along it. :func:`analyse` finds those
directions and names what they leave determined (:mod:`ceemx.lib.nullspace`);
:func:`identifiability_at` forms S and analyses it at (x, θ).

**Coordinates.** θ is learned unconstrained (:mod:`ceemx.models.constraints`). The analysis runs
in relative coordinates r: for a parameter whose natural value is nonzero, a unit of r is a change
of its log (d log|θ_nat| = θ_nat'(z)·dz / θ_nat, the constraint's forward derivative), so that a
symmetry such as (a, b, c) → (a·s, b/s, c/s) is the integer vector (1, −1, −1) and the determined
combinations are monomials (a·b, a·c); a parameter at zero gets the unit scale max(|z|, 1) of the
joint method's trust region.

**Thresholds.** A direction is *not determined* when its eigenvalue λ of the curvature in r is
below :data:`FLOOR` = 1: moving along it by one unit — a factor e in the parameters — changes J by
less than ½ nat, i.e. its Laplace standard deviation exceeds a factor e. This is a statistical
floor set by the noise, not a numerical one: on the product model of
``tests/test_identifiability.py`` a symmetry broken by a 10⁻³ term has λ = 0.01 (a standard
deviation of 10 e-folds; the determined combinations have λ ≈ 10⁵) while its eigenvalue in the
Jacobi-scaled D^(−½) S D^(−½), 4·10⁻⁸, would be at the edge of a relative cut-off of 10⁻⁸.
Directions with λ ≤ :data:`RCOND`·λ_max (10⁻¹⁰, a million times the unit rounding) are zero to
rounding and count too, whatever the floor (data so informative that rounding exceeds ½ nat).

**The stopping rule** of :class:`ceemx.JointLM` (``check_identifiability``). After an accepted
epoch whose J improvement is immaterial — at most ``check_rtol``·|J + c| = 10⁻⁶·|J + c|, 10⁴ ×
the solver's ``rtol``; |J + c| ≈ N/2 for N residuals at the noise floor, so below 0.05 nat up to
N = 10⁵, far below the ½ nat that separates statistically distinct fits — S is formed at the new
point the first time, and again whenever θ still moves: its step, scaled by max(|θ_i|, 1), is at
least :data:`NOT_SHRINKING` = ½ of the previous epoch's (a converging LM step shrinks ten-fold or
more per epoch). If at least :data:`STEP_SHARE` = 99 % of the step's squared length (in r) lies in
the not-determined subspace (its determined part at most 10 % of its length), the fit stops with
``converged=True``: what the data determine has converged, and further epochs would only move θ
along J's flat directions. Otherwise what the check found is kept and the fit goes on.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ceemx.identification.analysis.end_point import end_point
from ceemx.identification.fitting.term_progress import has_learned_term
from ceemx.identification.problem import FitProblem
from ceemx.identification.schur import schur_complement
from ceemx.infra.distributed import to_host
from ceemx.lib.nullspace import describe_null_space, near_null_space, share_in
from ceemx.lib.typing import PerTrajectory, States, Theta

__all__ = [
    "FLOOR",
    "MAX_P",
    "MIN_EPOCHS",
    "NOT_SHRINKING",
    "RCOND",
    "STEP_SHARE",
    "Identifiability",
    "analyse",
    "end_point_identifiability",
    "fit_identifiability",
    "identifiability_at",
    "relative_scale",
]

#: eigenvalue of the curvature in relative coordinates below which a direction is not determined
FLOOR = 1.0
#: eigenvalues ≤ RCOND·λ_max are zero to rounding
RCOND = 1e-10
#: share of the step's squared length in the not-determined subspace at which JointLM stops
STEP_SHARE = 0.99
#: JointLM checks only when the scaled θ-step is at least this fraction of the previous one
NOT_SHRINKING = 0.5
#: no analysis above this many parameters (a dense P × P eigen-analysis on the host: ~1 s at 2000)
MAX_P = 2000
#: a fit that did not converge is analysed at its end point only after at least this many epochs
#: (the analysis costs about one epoch: ≤ 5 % of such a fit; ``FitResult.check_identifiability``
#: runs it on demand)
MIN_EPOCHS = 20


@dataclasses.dataclass(frozen=True)
class Identifiability:
    """What the data do not determine, and what they do.

    Attributes:
        message: one sentence, e.g. "θ moved only along directions the data do not determine:
            only a·b and a·c are determined by the data (a, b, c individually are not); …".
        determined: the determined monomials, e.g. ``("a·b", "a·c")`` (empty when the
            non-determined directions are not monomial symmetries).
        exponents: for each determined monomial its ``(name, exponent)`` pairs.
        undetermined: the parameters taking part in a not-determined direction.
        eigenvalues: the curvature of each not-determined direction in relative coordinates
            (module notes: < 1 means a standard deviation above a factor e).
        step_share: the share of the last θ-step (squared length, relative coordinates) in the
            not-determined directions; NaN when no step was analysed (end point).
        stopped: whether :class:`ceemx.JointLM` stopped on it (``converged`` is then True for
            the determined combinations).
    """

    message: str
    determined: tuple[str, ...]
    exponents: tuple[tuple[tuple[str, int], ...], ...]
    undetermined: tuple[str, ...]
    eigenvalues: tuple[float, ...]
    step_share: float = float("nan")
    stopped: bool = False

    def to_record(self) -> dict[str, Any]:
        """A JSON-able dict (the fit history's ``identifiability`` entry)."""
        out = dataclasses.asdict(self)
        out["exponents"] = [[list(p) for p in e] for e in self.exponents]
        return out

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> Identifiability:
        """The inverse of :meth:`to_record` (e.g. from a checkpointed history)."""
        return cls(
            message=record["message"],
            determined=tuple(record["determined"]),
            exponents=tuple(tuple((str(n), int(k)) for n, k in e) for e in record["exponents"]),
            undetermined=tuple(record["undetermined"]),
            eigenvalues=tuple(float(v) for v in record["eigenvalues"]),
            step_share=float(record["step_share"]),
            stopped=bool(record["stopped"]),
        )


def relative_scale(problem: FitProblem, theta: Theta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(scale, loggable, natural_per_unit)`` of the relative coordinates r = θ / scale.

    ``loggable``: the natural value is nonzero and finite with a nonzero forward derivative, and
    either its constraint keeps it off zero (:meth:`FitProblem.sign_definite`) or |θ_nat| ≥ 1, so
    a unit of r is a unit of log|θ_nat| (scale = θ_nat / θ_nat'(z): signed, so that a unit of r
    multiplies a negative parameter by e as it does a positive one — with |θ_nat| it divided it,
    and a symmetry a·b → (a·s)·(b/s) with b < 0 read as a/b); otherwise scale = max(|z|, 1).
    ``natural_per_unit``: the change of the natural value per unit of r (θ_nat where loggable).
    """
    z = np.asarray(theta, dtype=np.float64)
    nat = np.asarray(problem.natural(theta), dtype=np.float64)
    slope = np.asarray(problem.natural_jacobian(theta), dtype=np.float64)
    tiny = np.finfo(np.float64).tiny
    loggable = np.isfinite(nat) & np.isfinite(slope) & (np.abs(nat) > tiny) & (np.abs(slope) > tiny)
    # A parameter that may change sign is measured relatively only where it is not small: a gain
    # fitted at 0.001 whose truth is 0 is determined to ±0.01, yet a factor e on it changes
    # nothing — in log units it would read "not determined". Below 1 it gets the unit scale.
    loggable &= problem.sign_definite(theta) | (np.abs(nat) >= 1.0)
    scale = np.where(loggable, nat / np.where(loggable, slope, 1.0), np.maximum(np.abs(z), 1.0))
    return scale, loggable, slope * scale


def analyse(problem: FitProblem, theta: Theta, S: Any, step: Any = None) -> Identifiability | None:
    """The not-determined directions of the curvature ``S`` at θ, named (module notes).

    Args:
        problem: the fit problem (parameter names and constraints).
        theta: (P,) θ in the problem's unconstrained coordinates.
        S: (P, P) the Schur complement at θ (host or device array).
        step: optional (P,) θ-step that led to θ: its share in the not-determined directions
            decides ``stopped`` (≥ :data:`STEP_SHARE`).

    Returns:
        An :class:`Identifiability`, or ``None`` when every direction is determined (or ``S`` is
        not finite). Host-side NumPy; one P × P eigen-analysis.
    """
    scale, loggable, per_unit = relative_scale(problem, theta)
    eigenvalues, basis = near_null_space(np.asarray(S), scale, floor=FLOOR, rcond=RCOND)
    if basis.shape[1] == 0:
        return None
    names = describe_null_space(basis, problem.parameter_names(), loggable, per_unit)
    share = float("nan") if step is None else share_in(basis, np.asarray(step) / scale)
    stopped = bool(share >= STEP_SHARE)
    lead = (
        "θ moved only along directions the data do not determine"
        if stopped
        else "the data do not determine every parameter"
    )
    message = (
        f"{lead}: {names.text}. Fix some of them (`trainable`), reparametrise, or add a prior "
        "(`log_prior`)."
    )
    return Identifiability(
        message,
        names.determined,
        names.exponents,
        names.undetermined,
        tuple(float(v) for v in eigenvalues),
        share,
        stopped,
    )


def identifiability_at(
    problem: FitProblem,
    theta: Theta,
    states: States,
    weights: PerTrajectory,
    step: Theta | np.ndarray | None = None,
) -> Identifiability | None:
    """:func:`analyse` of S at (x, θ) (:func:`ceemx.identification.schur.schur_complement`).

    ``None`` when every direction is determined, P > ``MAX_P`` (2000: the dense eigen-analysis
    is skipped) or S is unreliable. Costs one joint linearisation and Schur complement (about one
    epoch of the joint method; compiled once per problem shape) and a host P × P eigen-analysis.
    """
    if theta.shape[0] > MAX_P:
        return None
    S, ok = schur_complement(problem, theta, states, weights)
    if not bool(ok):
        return None
    return analyse(problem, theta, np.asarray(S), step)


def end_point_identifiability(
    problem: FitProblem, state: Any, history: list, converged: bool
) -> Identifiability | None:
    """The end-point analysis of a fit that did not converge after at least ``MIN_EPOCHS`` epochs.

    ``state`` is the fit's :class:`~ceemx.identification.solvers.base.FitState`. Shorter or
    converged fits are not analysed (``FitResult.check_identifiability`` does it on
    demand): the analysis costs about one epoch, ≤ 5 % of such a fit.
    """
    if converged or len(history) < MIN_EPOCHS or not np.any(to_host(state.weights) > 0):
        return None
    if has_learned_term(problem.build(state.theta)):  # a network's weights: never determined
        return None
    return identifiability_at(problem, state.theta, state.states, state.weights)


def fit_identifiability(result: Any) -> Identifiability | None:
    """:meth:`ceemx.FitResult.check_identifiability`: the fit's finding, else the end point's."""
    if result.identifiability is not None:
        return result.identifiability
    problem, theta, states, weights = end_point(result)
    return identifiability_at(problem, theta, states, weights)
