"""The fit-solver interface: ``init / step / terminate / postprocess`` over a :class:`FitState`.

A fit solver is an ``eqx.Module`` holding its options and declaring what it can do in class-level
flags (``learns_noise``, ``multi_process``, ``noise_rounds``, ``uncertainty``, ...), which the fit
machinery asks instead of testing the solver's type. The machinery (:func:`ceemx.fit`) owns
everything around it — validation, history, callbacks, progress, checkpoints, timing — and calls:

- ``init(problem, theta, states, key) -> FitState`` once (skipped on resume);
- ``step(problem, state) -> (state, record)`` once per epoch; ``record`` holds the solver's own
  history entries (documented in its ``history_keys``);
- ``terminate(problem, before, after, record) -> (stop, converged)`` after every epoch;
- ``postprocess(problem, state) -> state`` once at the end;
- ``identifiability(problem, state, history, converged)`` once after it (default ``None``);
- ``precompile(problem, theta, states)`` before all of these, in a background thread while the
  driver computes the start states: it compiles (never runs) the programs ``step`` will call, so
  that they compile beside the start-state smoother instead of after it (default: nothing).

Heavy work inside ``step`` runs in ``eqx.filter_jit``-compiled functions whose arguments keep their
shapes and dtypes across epochs, so an EM run compiles once. The driver converts the solver's
Python floats to arrays (:func:`ceemx.lib.trace_numbers`) before ``init``: new tolerances or
trust-region weights do not recompile either.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray, PyTree

from ceemx.identification import initialize
from ceemx.identification.analysis.identifiability import Identifiability
from ceemx.identification.learning.learners import AbstractLearner
from ceemx.identification.problem import FitProblem, per_trajectory_nll
from ceemx.inference.smoother import LMSmoother
from ceemx.infra.distributed import to_host
from ceemx.infra.options import check_nonnegative, check_rtol
from ceemx.infra.policy import Runs, program
from ceemx.lib.results import RESULTS, select
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta

__all__ = [
    "AbstractFitSolver",
    "check_alternation",
    "FitState",
    "improvement_converged",
    "objective_scale",
    "participating_sum",
    "starting_state",
    "total_J",
    "trajectory_log_likelihood",
]


class FitState(eqx.Module):
    """The iterate of a fit solver (what checkpoints hold, plus a transient cache).

    Attributes:
        theta: flat vector of the trainable parameters.
        states: (B, T, n) state trajectories.
        J: (B,) J_b(x_b, θ) (Eq. 9) of each trajectory at (``states``, ``theta``).
        weights: (B,) 1 for trajectories taking part, 0 for excluded (failed) ones.
        status: (B,) :class:`ceemx.RESULTS` per trajectory.
        solver_state: the solver's own arrays that persist across epochs (checkpointed).
        cache: recomputable data carried between epochs (e.g. a linearisation); never
            checkpointed — a solver must rebuild it when it is ``None``.
    """

    theta: Theta
    states: States
    J: PerTrajectory
    weights: PerTrajectory
    status: RESULTS
    solver_state: PyTree = None
    cache: PyTree = None


def trajectory_log_likelihood(problem: FitProblem, theta: Theta, states: States) -> PerTrajectory:
    """(B,) J_b(x_b, θ), compiled once per problem shape (``problem.per_trajectory_nll``)."""
    return -per_trajectory_nll(problem, theta, states)


@program(runs=Runs.ONCE)
def _offset(problem: FitProblem, theta: Theta, weights: PerTrajectory) -> Scalar:
    return problem.offset(theta, weights)


def starting_state(
    problem: FitProblem, theta: Theta, states: States, solver_state: PyTree = None
) -> FitState:
    """θ and x as given, every trajectory taking part and ``successful``, J evaluated."""
    B = states.shape[0]
    return FitState(
        theta=theta,
        states=states,
        J=trajectory_log_likelihood(problem, theta, states),
        weights=jnp.ones((B,), states.dtype),
        status=select(jnp.zeros((B,), bool), RESULTS.nonfinite, RESULTS.successful),
        solver_state=solver_state,
    )


def participating_sum(values, weights) -> float:
    """Σ_b of per-trajectory ``values`` over the trajectories with weight > 0 (host-side).

    NaN when none takes part: an empty sum of 0.0 would read as a finite, even a good, objective
    in the history of an epoch whose every trajectory failed.
    """
    w = to_host(weights)
    if not np.any(w > 0):
        return float("nan")
    return float(np.sum(np.where(w > 0, to_host(values), 0.0)))


def total_J(state: FitState) -> float:
    """Σ_b J_b over the trajectories taking part (:func:`participating_sum`)."""
    return participating_sum(state.J, state.weights)


def improvement_converged(
    problem: FitProblem, before: FitState, after: FitState, rtol, atol
) -> bool:
    """Algorithm 1's rule, made relative: J improved by at most ``rtol·|J + c| + atol``.

    c is the sum of the noise models' −log p at zero residual, so |J + c| is ½‖whitened
    residuals‖² for Gaussian noise: the tolerance is measured against the fit, not against
    normalising constants that can dwarf it.
    """
    J_before, J_after = total_J(before), total_J(after)
    if not np.isfinite(J_after):
        return False
    return bool(J_after - J_before <= float(rtol) * objective_scale(problem, after) + float(atol))


def objective_scale(problem: FitProblem, state: FitState) -> float:
    """|J + c| at ``state``: ½‖whitened residuals‖² for Gaussian noise (the scale of rtol)."""
    return abs(total_J(state) + float(_offset(problem, state.theta, state.weights)))


def check_alternation(smoother, learner, rho_theta) -> None:
    """Validate the options of a smoothing + learning solver (Alternating, LaplaceEM)."""
    if not isinstance(smoother, LMSmoother):
        raise TypeError(f"`smoother` must be a ceemx.LMSmoother; got {smoother!r}.")
    if not isinstance(learner, AbstractLearner):
        raise TypeError(f"`learner` must be a ceemx learner; got {learner!r}.")
    check_nonnegative("rho_theta", rho_theta)


class AbstractFitSolver(eqx.Module):
    """A method that maximises the CE-EM objective J(x, θ) epoch by epoch (see module docs).

    Attributes:
        rtol, atol: tolerances of the stopping rule (see each solver).
    """

    rtol: eqx.AbstractVar[float]
    atol: eqx.AbstractVar[float]

    #: The solver's own history entries: name → meaning (the driver adds ``epoch``, ``time``,
    #: ``J``, ``J_before``, ``J_per_trajectory``, ``dtheta_norm``, ``dx_norm``,
    #: ``failed_trajectories``, ``converged``, ``stop``).
    history_keys: ClassVar[Mapping[str, str]] = {}

    #: Whether the method can learn noise covariances (only :class:`ceemx.LaplaceEM`: the CE-EM
    #: objective J grows without bound as a noise scale → 0, so CE methods refuse them).
    learns_noise: ClassVar[bool] = False
    #: Whether the method runs on data spread over several processes (``fit(devices=...)``): every
    #: value it reads on the host is gathered across them (or needs no gathering).
    multi_process: ClassVar[bool] = False
    #: Whether ``fit(..., noise="learn")`` may wrap it: a certainty-equivalent method, maximising
    #: J(x, θ) at the noise it is given (the rounds re-estimate that noise between fits).
    noise_rounds: ClassVar[bool] = False
    #: The parameter covariance of its result (:meth:`ceemx.FitResult.covariance`):
    #: ``"certainty-equivalent"`` — the Laplace approximation of p(x, θ | y) at the end point, the
    #: Schur complement of J's Gauss–Newton matrix — or ``"evidence"`` — the inverse observed
    #: information of the Laplace log-evidence with the method's own ``smoother``.
    uncertainty: ClassVar[Literal["certainty-equivalent", "evidence"]] = "certainty-equivalent"
    #: Whether the epochs smooth with the warm start's program (:func:`ceemx.smooth`'s; Algorithm
    #: 1): the warm start then smooths :attr:`~ceemx.infra.policy.Runs.EVERY_EPOCH`, one program
    #: for both; otherwise (the joint method, Laplace EM) :attr:`~ceemx.infra.policy.Runs.ONCE`.
    smooths_each_epoch: ClassVar[bool] = False
    #: Whether a certainty-equivalent fit warm-started next to its answer settles in a few epochs
    #: (the joint method): :meth:`ceemx.FitResult.profile` refits with it; one without it
    #: (Algorithm 1) is profiled by :class:`ceemx.JointLM` refits, the same J (Laplace EM's
    #: profile, of the evidence, refits with Laplace EM).
    warm_refits: ClassVar[bool] = False
    #: The history entry no epoch lowers (up to round-off), or ``None`` where none is promised:
    #: ``"J"`` for a method that keeps only steps that raise J (Algorithm 1's coordinate ascent,
    #: the joint LM); ``"log_evidence"`` for Laplace EM (EM's ascent property, exact on models
    #: linear-Gaussian in the state, kept by its accelerations' safeguards); ``None`` for a
    #: stochastic method (particle EM).
    monotone: ClassVar[str | None] = None

    def __check_init__(self):
        # Equinox runs every class's __check_init__: each solver's own checks come on top.
        check_rtol("rtol", self.rtol)
        check_nonnegative("atol", self.atol)

    def initial_states(self, system, data) -> States:
        """The start states of ``fit(..., x_init=None)``: ``initialize.warm_start``'s.

        ``system`` and ``data`` come prepared (:func:`ceemx.data.checks.prepare`).

        Least squares through the observation map, then one smoothing pass at the initial θ
        with weak dynamics weights, which fills in the unobserved directions from the dynamics
        (a start at zero velocity, say, can lead a joint method to a poor stationary point).
        A solver with its own ``smoother`` (Algorithm 1, Laplace EM) warm-starts in that
        smoother's ``batch_chunk`` (memory bound for large n).
        """
        own = getattr(self, "smoother", None)
        # without one, the default smoother: the same program as the end-of-fit smoothing check's
        smoother = (
            LMSmoother(batch_chunk=own.batch_chunk) if isinstance(own, LMSmoother) else LMSmoother()
        )
        runs = Runs.EVERY_EPOCH if self.smooths_each_epoch else Runs.ONCE
        return initialize.warm_start_states(system, data, smoother=smoother, runs=runs)

    def check_problem(self, problem: FitProblem, theta: Theta) -> None:
        """Refuse a problem this method cannot fit, before any compute (:func:`ceemx.fit`).

        Default: noise models selected by ``trainable`` are refused unless the method
        ``learns_noise`` (the certainty-equivalent J grows without bound as a noise scale → 0).
        """
        del theta
        noise = [f for f in ("process_noise", "obs_noise") if problem.trains(f)]
        if noise and not self.learns_noise:
            raise ValueError(
                f"`trainable` selects the noise model{'s' if len(noise) > 1 else ''} "
                f"{', '.join('system.' + f for f in noise)}, but {type(self).__name__} "
                "maximises the certainty-equivalent J(x, θ), which grows without bound as a noise "
                "scale → 0 (the states absorb the residuals): noise cannot be learned by it. Use "
                "solver=ceemx.LaplaceEM(), which learns noise covariances by EM, or fix the noise."
            )

    def precompile(
        self, problem: FitProblem, theta: Theta, states: States
    ) -> Sequence[Callable[[], object]]:
        """Jobs compiling the programs of ``step`` for these shapes, without running them.

        :func:`ceemx.fit` runs them in a background thread, largest first
        (where :func:`ceemx.infra.policy.compiles_ahead`; the main thread takes the ones
        still waiting when its start states are ready) with the problem, θ and start states
        ``init`` will receive (the states may be placeholders of the right shape and dtype,
        computed meanwhile). A job only does ``lower(...).compile()`` of a program, with
        arguments of exactly the shapes, dtypes and static parts of the later calls; nothing
        may execute. Default: none.
        """
        del problem, theta, states
        return ()

    @abc.abstractmethod
    def init(
        self, problem: FitProblem, theta: Theta, states: States, key: PRNGKeyArray
    ) -> FitState:
        """The initial state at (θ, x)."""

    @abc.abstractmethod
    def step(self, problem: FitProblem, state: FitState) -> tuple[FitState, dict[str, Any]]:
        """One epoch; returns the new state and the solver's history entries (JSON-able)."""

    def terminate(
        self, problem: FitProblem, before: FitState, after: FitState, record: dict[str, Any]
    ) -> tuple[bool, bool]:
        """(stop, converged) after an epoch. Default: :func:`improvement_converged`."""
        if not np.any(to_host(after.weights) > 0):
            return True, False  # every trajectory failed: nothing left to fit
        converged = improvement_converged(problem, before, after, self.rtol, self.atol)
        return converged, converged

    def end_check(
        self, problem: FitProblem, state: FitState
    ) -> tuple[FitState, bool | None, dict[str, Any]]:
        """A check of the epochs' end point, after them: (state, verdict, record).

        ``verdict``: whether the end point is an optimum (``None``: no verdict — the epochs'
        stands); a non-empty ``record`` joins the history as one more record. Default: none
        (``state``, ``None``, ``{}``); :class:`ceemx.LaplaceEM` with ``polish``: Newton on the
        Laplace evidence.
        """
        return state, None, {}

    def postprocess(self, problem: FitProblem, state: FitState) -> FitState:
        """The final state (default: unchanged)."""
        return state

    def identifiability(
        self, problem: FitProblem, state: FitState, history: list, converged: bool
    ) -> Identifiability | None:
        """What the fit found about the parameters the data do not determine (default: nothing).

        Called once by :func:`ceemx.fit` after ``postprocess``; the result is
        :attr:`ceemx.FitResult.identifiability`.
        """
        return None
