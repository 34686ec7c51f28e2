"""The method ``fit`` runs without a solver, chosen from the problem: :func:`choose`.

The rule, from the problem's size and what the user fixed (``docs/api/fit.md``, "The default
path"; the measurements behind it in ``docs/decisions.md``):

1. ``trainable`` selects noise models → :class:`~ceemx.LaplaceEM` alone (the one method that
   learns noise covariances).
2. More than :data:`MAX_JOINT_PARAMETERS` entries in θ (neural and hybrid models) →
   :class:`~ceemx.Alternating`, the paper's Algorithm 1, at the given noise (``noise="learn"``
   on request): its learner updates θ alone, where the joint method and Laplace EM carry dense
   P × P blocks; and the evidence of a model flexible enough to interpolate the data has its
   maximum at a noise → 0, so the noise of such a model is not learned unasked.
3. Data spread over several processes → :class:`~ceemx.JointLM` alone at the given noise (the
   noise estimate and Laplace EM read per-trajectory values on one host).
4. Noise models without a closed-form update (not Gaussian) → :class:`~ceemx.JointLM` alone at
   the given noise.
5. Otherwise two stages: :class:`~ceemx.JointLM` with the noise learned from the data
   (``fit(noise="learn")``; at the given noise with ``noise="fixed"``), then
   :class:`~ceemx.LaplaceEM` in θ alone at that noise, from the joint fit's θ and states. The
   joint method reaches the certainty-equivalent optimum in a few epochs; the Laplace finish
   moves θ to the maximiser of the Laplace evidence, which removes the certainty-equivalent
   bias, and its intervals are the evidence's (the states integrated out). On long data (B·T ≥
   :data:`LONG_STEPS`) the noise is learned on their first :data:`NOISE_PART_STEPS` steps (the
   noise scales are two numbers, which a part determines to a percent or so; learning them on
   every step costs ten joint fits), and the finish takes quasi-Newton steps
   (``acceleration="quasi_newton"``, after its own coarse start on the first 10 000 steps).
   The finish stops when an epoch changes the log-evidence by less than :data:`FINISH_ATOL`,
   or at the first epoch that lowers it by more (where the model is curved in the state, EM's
   fixed point lies past the evidence's maximum); on short data and θ of at most
   :data:`~ceemx.identification.solvers.laplace_newton.POLISH_MAX_PARAMETERS` entries it then
   tests the end point on the evidence itself and takes Newton steps to its maximum
   (``LaplaceEM(polish=True)``: the evidence's gradient and Hessian by finite differences, a
   few hundred smoothings at most; on long data each smoothing is of all of them).
   The finish is skipped, and says why, when the joint fit's covariance is not positive definite
   (:func:`~ceemx.identification.fitting.default_path.fit_default`): a noise learned degenerate —
   a process noise → 0 on data without any — where Laplace EM creeps for its whole epoch budget
   and its evidence covariance is not finite either.

A solver the user names runs as named; the noise is then the given one unless ``noise="learn"``.
:class:`Choice` records what was chosen and why (``FitResult.choice``, the summary's "solver"
line), and, once run (:mod:`~ceemx.identification.fitting.default_path`), each stage's epochs,
convergence and time.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from ceemx.identification.noise_moments import (
    COARSE_FACTOR,
    COARSE_STEPS,
    NOISE_FIELDS,
    coarse_shape,
)
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.alternating import Alternating
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.identification.solvers.joint import JointLM
from ceemx.identification.solvers.laplace import LaplaceEM
from ceemx.identification.solvers.laplace_newton import POLISH_MAX_PARAMETERS
from ceemx.identification.solvers.laplace_qn import QN_MAX_PARAMETERS
from ceemx.lib.typing import Theta
from ceemx.models.system import AbstractSystem

__all__ = [
    "LONG_STEPS",
    "MAX_JOINT_PARAMETERS",
    "FINISH_ATOL",
    "NOISE_PART_STEPS",
    "Choice",
    "Stage",
    "choose",
    "problem_facts",
]

#: the most θ entries for which the joint method and the Laplace finish are chosen: both carry
#: dense P × P blocks (the quasi-Newton finish's curvature is limited to this size)
MAX_JOINT_PARAMETERS = QN_MAX_PARAMETERS
#: data of at least this many time steps (B·T) are long: their noise is learned on a part, and
#: the Laplace finish takes quasi-Newton steps (where Laplace EM and the noise estimate start
#: from a coarse part of the data too)
LONG_STEPS = COARSE_FACTOR * COARSE_STEPS
#: the time steps of the part of long data the noise is learned on
NOISE_PART_STEPS = 2_500

#: nats: the Laplace finish stops once an epoch changes the log-evidence by less. A change that
#: small is statistically nothing (an interval's end moves the evidence by 1.92 nats), and even at
#: an EM rate of 0.99 the epochs left would add under 1e-3 nats. The solver's own relative
#: tolerance (1e-10 of |J|) lies below the Laplace approximation's accuracy for a nonlinear model,
#: where EM's ascent is not exact and an epoch's change can stay above it for the whole budget.
FINISH_ATOL = 1e-5

Noise = Literal["fixed", "learn"]
StageNoise = Literal["fixed", "learn", "parameters"]


@dataclasses.dataclass(frozen=True)
class Stage:
    """One fit of a path: its solver, its noise, the data it sees and, once run, what it did.

    Attributes:
        solver: the fit solver.
        noise: ``"learn"`` (``fit(noise="learn")``: rounds of fits and noise estimates),
            ``"fixed"`` (the noise it is given: the user's, or the previous stage's) or
            ``"parameters"`` (selected by ``trainable``: learned by the solver, in θ).
        part: ``(b, t)``: the first b trajectories cut to their first t steps (long data), or
            ``None``: all of them.
        epochs, converged, seconds: filled in once the stage has run (epochs of every noise
            round together; seconds of wall time).
        skipped: why the stage did not run (``None``: it ran, or has not yet).
        discarded: why the stage's result was set aside after it ran (``None``: it stands).
        restarted: the parameters this stage started from their start values, not from the
            previous stage's: it left them at their bound, where no step moves them.
    """

    solver: AbstractFitSolver
    noise: StageNoise = "fixed"
    part: tuple[int, int] | None = None
    epochs: int | None = None
    converged: bool | None = None
    seconds: float | None = None
    skipped: str | None = None
    discarded: str | None = None
    restarted: tuple[str, ...] = ()

    def describe(self, first: bool = True) -> str:
        """E.g. ``"JointLM (noise learned on the first 2500 steps)"``."""
        name = type(self.solver).__name__
        if getattr(self.solver, "acceleration", None) == "quasi_newton":
            name += " (quasi-Newton)"
        where = ""
        if self.part is not None:
            b, t = self.part
            where = f" on the first {t} steps" + (f" of {b} trajectories" if b > 1 else "")
        if self.noise == "learn":
            return f"{name} (noise learned{where})"
        if self.noise == "parameters":
            return f"{name} (noise learned as parameters)"
        if first:
            return f"{name} (noise as given{where})"
        return f"{name} in θ at that noise"


@dataclasses.dataclass(frozen=True)
class Choice:
    """The method a fit ran and why (:attr:`ceemx.FitResult.choice`).

    Attributes:
        stages: the fits run one after the other, each from the previous one's θ, noise and
            states (one for a single solver).
        reason: why, in words (the summary's "because ...").
        by: ``"library"`` (``fit`` without a solver: :func:`choose`) or ``"user"``.
        seconds: wall time of the whole fit (``None`` until run).
    """

    stages: tuple[Stage, ...]
    reason: str
    by: Literal["library", "user"] = "library"
    seconds: float | None = None

    @property
    def learns_noise(self) -> bool:
        """Whether a stage learns the noise (in rounds that do not checkpoint)."""
        return any(s.noise == "learn" for s in self.stages)

    def describe(self) -> str:
        """The path in words, e.g. "JointLM (noise learned), then LaplaceEM in θ at that noise"."""
        return ", then ".join(
            s.describe(i == 0)
            + (f" — skipped: {s.skipped}" if s.skipped else "")
            + (
                f" (from the start's {', '.join(s.restarted)}: the previous stage left "
                f"{'it' if len(s.restarted) == 1 else 'them'} at the bound)"
                if s.restarted
                else ""
            )
            + (f" — discarded: {s.discarded}" if s.discarded else "")
            for i, s in enumerate(self.stages)
        )


def choose(
    *,
    parameters: int,
    steps: tuple[int, int],
    noise: Noise | None = None,
    gaussian: bool = True,
    trains_noise: bool = False,
    spread: bool = False,
    placed: bool = False,
) -> Choice:
    """The method ``fit`` runs without a solver, from the problem (the rule: module notes).

    Args:
        parameters: P, the number of entries of θ (the trainable leaves' sizes together).
        steps: ``(B, T)``, the data's trajectories and time steps.
        noise: ``fit``'s ``noise``: ``None`` (the library decides: learned where it can be),
            ``"fixed"`` or ``"learn"``.
        gaussian: whether both noise models have a closed-form update (can be learned).
        trains_noise: whether ``trainable`` selects a noise model.
        spread: whether the data are spread over several processes.
        placed: whether the data are placed on several devices (``fit(devices=...)``): the
            noise is then learned on all of them (a part need not divide among the devices).

    Returns:
        The :class:`Choice`.

    Raises:
        ValueError: ``noise="learn"`` where ``trainable`` already selects the noise models.
    """
    B, T = steps
    size = f"{parameters} parameter{'s' if parameters != 1 else ''} and {B * T} time steps"
    if trains_noise:
        if noise == "learn":
            raise ValueError(
                "`trainable` selects noise models, which LaplaceEM learns as parameters; "
                "noise='learn' learns them in rounds of certainty-equivalent fits instead. "
                "Pass one or the other."
            )
        return Choice(
            (Stage(LaplaceEM(), "parameters"),),
            "`trainable` selects noise models: LaplaceEM is the method that learns noise "
            "covariances",
        )
    given: Noise = "learn" if noise == "learn" else "fixed"
    if parameters > MAX_JOINT_PARAMETERS:
        return Choice(
            (Stage(Alternating(), given),),
            f"{size}: more than {MAX_JOINT_PARAMETERS} parameters, where the joint method's "
            "and Laplace EM's dense P × P blocks cost most; Algorithm 1's learner updates θ "
            "alone, and the noise of a model that flexible stays as given unless "
            "noise='learn' (its evidence can peak at a noise → 0)",
        )
    if spread:
        return Choice(
            (Stage(JointLM(), given),),
            f"{size}, spread over several processes: the joint method; Laplace EM and the "
            "noise estimate read per-trajectory values on one host",
        )
    if not gaussian:
        return Choice(
            (Stage(JointLM(), given),),
            f"{size}; the noise models have no closed-form update (not Gaussian): the joint "
            "method at the given noise; neither the noise estimate nor the Laplace finish "
            "applies",
        )
    learn = noise != "fixed"
    long = B * T >= LONG_STEPS
    part = coarse_shape(B, T, NOISE_PART_STEPS) if (learn and long and not placed) else None
    finish = LaplaceEM(
        acceleration="quasi_newton" if long else "squarem",
        atol=FINISH_ATOL,
        polish=not long and parameters <= POLISH_MAX_PARAMETERS,
    )
    noise_words = "the noise learned from the data" if learn else "the noise as given"
    reason = (
        f"{size}: the joint method (fast where parameters are few) with {noise_words}, then a "
        "Laplace-EM finish in θ, which removes the certainty-equivalent bias"
    )
    if long:
        first = "the noise from their first part, " if part is not None else ""
        reason += f"; long data (≥ {LONG_STEPS} steps): {first}quasi-Newton finish"
    return Choice((Stage(JointLM(), "learn" if learn else "fixed", part), Stage(finish)), reason)


def problem_facts(
    problem: FitProblem,
    theta: Theta,
    system: AbstractSystem,
    spread: bool = False,
    placed: bool = False,
) -> dict:
    """The keyword arguments of :func:`choose` that come from the problem (all but ``noise``)."""
    noise_models = [getattr(system, f, None) for f in NOISE_FIELDS]
    return {
        "parameters": int(np.size(theta)),
        "steps": tuple(int(s) for s in problem.data.y.shape[:2]),
        "gaussian": all(
            m is not None and bool(getattr(m, "learnable_in_closed_form", False))
            for m in noise_models
        ),
        "trains_noise": any(problem.trains(f) for f in NOISE_FIELDS),
        "spread": spread,
        "placed": placed,
    }
