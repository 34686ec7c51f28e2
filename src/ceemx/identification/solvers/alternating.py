"""Algorithm 1 of the paper: alternate a smoothing step (Eq. 10) and a learning step (Eq. 11)."""

from __future__ import annotations

import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from ceemx.identification.analysis.identifiability import end_point_identifiability
from ceemx.identification.learning import learners as _learners
from ceemx.identification.learning import step as learning_step
from ceemx.identification.learning.learning_problem import learning_problem
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import (
    AbstractFitSolver,
    FitState,
    check_alternation,
    starting_state,
    trajectory_log_likelihood,
)
from ceemx.inference import smoother as smoothing_solver
from ceemx.infra.distributed import to_host
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, codes, select
from ceemx.lib.typing import States, Theta

__all__ = ["E_STEP_MAX_STEPS", "Alternating"]

#: The smoothing step's LM bound in :class:`Alternating`'s default smoother (a partial E-step).
E_STEP_MAX_STEPS = 2


class Alternating(AbstractFitSolver):
    """CE-EM by block coordinate ascent (paper Algorithm 1).

    Each epoch smooths every trajectory at the current θ (``smoother``, Eq. 10, with its trust
    region ρ_x), then learns θ on the smoothed states (``learner``, Eq. 11, with the trust region
    ``rho_theta`` and the problem's log-prior). Trajectories whose smoothing fails (non-finite
    objective) are excluded from learning and reported. Stops when J improves by at most
    ``rtol·|J + c| + atol`` in an epoch (c: the noise models' normalising constants). A fit that
    did not converge in at least 20 epochs is analysed at its end point for parameters the data
    do not determine (:attr:`ceemx.FitResult.identifiability`).

    Attributes:
        smoother: the smoothing-step solver (:class:`ceemx.LMSmoother`). Default
            ``LMSmoother(max_steps=2)``: a partial E-step (at most two accepted-or-rejected LM
            steps from the previous epoch's states; J still rises every epoch): per epoch as
            good as smoothing to convergence, for less time; pass ``LMSmoother()`` to smooth
            fully.
        learner: the learning-step optimiser (:class:`ceemx.LMLearner`, L-BFGS, Optax,
            Nelder–Mead). Default ``LMLearner(max_accepted=1)``: a generalised-EM M-step (one
            Gauss–Newton build and its first accepted step per epoch; J still rises every
            epoch): per epoch as good as the exact M-step (several builds) at a fraction of the
            cost; pass ``LMLearner()`` for an exact one.
        rho_theta: ρ_θ ≥ 0 of Eq. 11.
        rtol, atol: stopping rule on the improvement of J per epoch.
    """

    smoother: smoothing_solver.LMSmoother = eqx.field(
        default_factory=lambda: smoothing_solver.LMSmoother(max_steps=E_STEP_MAX_STEPS)
    )
    learner: _learners.AbstractLearner = eqx.field(
        default_factory=lambda: _learners.LMLearner(max_accepted=1)
    )
    rho_theta: float = 0.0
    rtol: float = 1e-10
    atol: float = 0.0

    smooths_each_epoch = True  # the E-step is the warm start's program: compiled optimised once
    multi_process = True
    noise_rounds = True
    monotone = "J"
    history_keys = {
        "smooth_time": "seconds in the smoothing step",
        "learn_time": "seconds in the learning step",
        "smoother_steps": "most LM iterations any trajectory took in the smoothing step",
        "learner_steps": "iterations of the learner",
        "learner_status": "the learner's RESULTS code",
    }

    def __check_init__(self):
        check_alternation(self.smoother, self.learner, self.rho_theta)

    def check_problem(self, problem: FitProblem, theta: Theta) -> None:
        """The base class's refusals, and the learner's memory guard, before any compute.

        (The first learning step would otherwise refuse only after the warm start and a
        smoothing step.)
        """
        super().check_problem(problem, theta)
        self.learner.check_memory(theta.shape[0], problem.data.batch_size, theta.dtype.itemsize)

    def init(
        self, problem: FitProblem, theta: Theta, states: States, key: PRNGKeyArray
    ) -> FitState:
        """θ, x as given; all trajectories take part; the learner's state from ``key``."""
        return starting_state(problem, theta, states, self.learner.init(theta, key))

    def step(self, problem: FitProblem, state: FitState) -> tuple[FitState, dict]:
        """One smoothing step and one learning step."""
        t0 = time.perf_counter()
        system = problem.build(state.theta)
        sol = smoothing_solver.smooth_batch(
            self.smoother, system, state.states, problem.data, False
        )
        sol.states.block_until_ready()
        t_smooth = time.perf_counter() - t0
        failed = to_host(sol.status == RESULTS.nonfinite)
        if failed.any():
            warn(
                f"smoothing failed (non-finite objective) on trajectories "
                f"{np.flatnonzero(failed).tolist()}; they are excluded from learning."
            )
        weights = jnp.asarray(np.where(failed, 0.0, 1.0), state.states.dtype)

        t0 = time.perf_counter()
        lp = learning_problem(problem, state.theta, sol.states, weights, self.rho_theta)
        theta, learner_state, info = learning_step.run_learner(
            self.learner, lp, state.theta, state.solver_state
        )
        theta.block_until_ready()
        t_learn = time.perf_counter() - t0
        # A smoothing step that used its whole LM budget is a partial E-step, not a failure: the
        # fit's convergence is judged on J (the default smoother is bounded to 2 steps).
        status = select(sol.status == RESULTS.max_steps_reached, RESULTS.successful, sol.status)
        new = FitState(
            theta=theta,
            states=sol.states,
            J=trajectory_log_likelihood(problem, theta, sol.states),
            weights=weights,
            status=status,
            solver_state=learner_state,
        )
        record = {
            "smooth_time": t_smooth,
            "learn_time": t_learn,
            "smoother_steps": int(np.max(to_host(sol.iterations))),
            "learner_steps": int(info.steps),
            "learner_status": int(codes(info.status)),
        }
        return new, record

    def identifiability(self, problem, state, history, converged):
        """At the end of a fit that did not converge: ``end_point_identifiability``."""
        return end_point_identifiability(problem, state, history, converged)
