"""Joint Levenberg–Marquardt on (x, θ) through the Schur complement (beyond the paper).

The paper minimises −J(x, θ) by alternating blocks (Algorithm 1). Alternation is slow when x and θ
are strongly coupled; a joint second-order step uses that coupling. Its normal equations are an
arrowhead: per trajectory b a block-tridiagonal A_b = J_xᵀWJ_x, a shared dense D = Σ_b J_θᵀWJ_θ,
and the border E_b = J_xᵀWJ_θ (shape (T, n, theta)). :func:`ceemx.lib.arrowhead_solve` eliminates
x through the Schur complement S = D − Σ_b E_bᵀA_b⁻¹E_b (P × P, P the length of θ) in
O(B T (n³ + n² P) + P³) — or matrix-free CG on S for P > ``dense_max_p`` — and recovers the x-step
by block back-substitution.

Each epoch is one accepted Levenberg–Marquardt step with Marquardt's per-variable damping (scale
invariance across parameters of different magnitudes), accepted on actual vs predicted decrease.
ρ_x and ρ_θ are proximal terms centred at the current iterate (they add 2ρ to the curvature of
their block, as in Eq. 10–11); the log-prior is part of the objective. An epoch linearises once,
at its start point; trial points are judged by the objective's value alone, so an epoch costs one
linearisation, one arrowhead solve and one evaluation per trial, and nothing is carried between
epochs (the linearisation, with its B·T·n·P border, is not kept in memory across the driver's
host work).

Two guards make it safe from a poor start (a joint Gauss–Newton model far from the optimum can
propose a step that moves a log-parameter by hundreds):

- a trust region in scaled variables: a trial step whose largest θ move exceeds
  ``max_theta_step·max(|θ_i|, 1)`` is shortened, (δx, δθ) together, to that bound (the shortened
  LM step is still a descent direction of the model; acceptance compares actual and predicted
  decrease of the shortened step as usual);
- a smoothing check before stopping: when the iteration would stop (converged, or stuck), one
  smoothing pass at the end θ (:class:`ceemx.LMSmoother`) is tried; if it raises J by more than
  ``check_rtol·|J + c|``, its states are taken and the iterations go on (history key
  ``smoothing_gain``), so a point that the alternating method's own smoothing step would leave
  is never reported as converged.

A third guard stops it from wandering where the data say nothing: when J has stopped improving
materially but θ still moves, the Schur complement S at the new point tells whether the step lies
in directions the data do not determine (``check_identifiability``,
:mod:`ceemx.identification.analysis.identifiability`); if so the fit stops, converged in what the
data determine, and the result names it ("only a·b and a·c are determined by the data").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from ceemx import lib
from ceemx.identification import schur
from ceemx.identification.analysis.identifiability import (
    MAX_P,
    NOT_SHRINKING,
    Identifiability,
    end_point_identifiability,
    identifiability_at,
)
from ceemx.identification.fitting.term_progress import has_learned_term
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers import joint_matrix_free
from ceemx.identification.solvers.base import (
    AbstractFitSolver,
    FitState,
    improvement_converged,
    objective_scale,
    trajectory_log_likelihood,
)
from ceemx.inference import smoother as smoothing_solver
from ceemx.infra.distributed import to_host
from ceemx.infra.memory import check_fits
from ceemx.infra.options import (
    check_bool,
    check_choice,
    check_damping,
    check_int,
    check_nonnegative,
    check_positive,
    check_rtol,
)
from ceemx.infra.policy import Runs, joint_iteration_work, program
from ceemx.infra.warn import warn
from ceemx.lib.lm import levenberg_marquardt, marquardt_scale
from ceemx.lib.results import RESULTS, codes, select
from ceemx.lib.tree import as_jax, trace_numbers
from ceemx.lib.typing import PerTrajectory, Scalar, States, Theta

__all__ = ["JointLM"]


class JointLM(AbstractFitSolver):
    """Levenberg–Marquardt on (x, θ) together, with the arrowhead Schur-complement solve.

    On strongly coupled problems (coupled Lorenz) it reaches in a handful of iterations what
    Algorithm 1 needs hundreds of epochs for. One epoch is one accepted LM step. Stops when J
    improves by at most ``rtol·|J + c| + atol`` (Algorithm 1's rule), when the model predicts no
    further decrease, or when no step is accepted within ``max_trials`` (reported by status), or
    — converged in what the data determine — when θ moves only along directions the data do not
    determine (``check_identifiability``). Trajectories whose objective is not finite at the
    start take no part (status ``nonfinite``).

    Attributes:
        rho_x: proximal weight on the states (adds 2ρ_x to their curvature every iteration).
        rho_theta: proximal weight on θ.
        rtol, atol: stopping rule on the improvement of J (and the LM's predicted decrease).
        damping: initial Marquardt λ (> 0 and below 1/rtol: :mod:`ceemx.infra.options`).
        max_trials: bound on rejected trials within one iteration.
        linear_solver: ``"auto"`` (dense Schur complement when P ≤ ``dense_max_p``, otherwise
            matrix-free preconditioned CG on S), ``"dense"`` or ``"cg"``.
        dense_max_p: threshold of ``"auto"``.
        cg_rtol: relative residual tolerance of CG.
        cg_max_steps: CG iteration bound (``None``: P; with the matrix-free border, min(P, 100)).
        border: ``"dense"`` (E_b, D formed: B·T·n·P and P² numbers) or ``"matrix-free"``: E_b,
            E_bᵀ and D applied as Jacobian-vector products, S by preconditioned CG, truncated at
            ``cg_rtol``/``cg_max_steps`` (an inexact Newton step): memory O(B·T·n² + P), for P
            in the tens of thousands (:mod:`ceemx.identification.solvers.joint_matrix_free`).
            ``linear_solver`` and ``dense_max_p`` do not apply to it.
        border_scaling: with ``border="matrix-free"``, θ's damping scale and CG's Jacobi
            preconditioner: ``"diagonal"`` (exact diag(D), about one dense θ-Jacobian's work
            per iteration, one time step at a time) or ``"identity"`` (Levenberg damping in θ,
            no preconditioner).
        max_theta_step: trust region of one step, in scaled variables: no θ_i moves by more than
            ``max_theta_step·max(|θ_i|, 1)`` (``inf``: unbounded).
        check_smoothing: before stopping, try one smoothing pass at the end θ and go on if it
            raises J by more than ``check_rtol·|J + c|`` (see the module notes).
        check_rtol: the material improvement of J, relative to |J + c|: of the smoothing check,
            and below which the identifiability check looks at the step.
        check_identifiability: when J improved by at most ``check_rtol·|J + c|`` in an epoch but
            θ still moved, form S at the new point and stop if the step lies in directions the
            data do not determine (:mod:`ceemx.identification.analysis.identifiability`:
            thresholds and why; skipped above P = 2000). The result's ``identifiability`` names
            them.
    """

    rho_x: float = 0.0
    rho_theta: float = 0.0
    rtol: float = 1e-10
    atol: float = 0.0
    damping: float = 1e-3
    max_trials: int = eqx.field(default=30, static=True)
    linear_solver: str = eqx.field(default="auto", static=True)
    dense_max_p: int = eqx.field(default=5000, static=True)
    cg_rtol: float = 1e-12
    cg_max_steps: int | None = eqx.field(default=None, static=True)
    max_theta_step: float = 1.0
    check_smoothing: bool = eqx.field(default=True, static=True)
    check_rtol: float = 1e-6
    check_identifiability: bool = eqx.field(default=True, static=True)
    border: str = eqx.field(default="dense", static=True)
    border_scaling: str = eqx.field(default="diagonal", static=True)

    multi_process = True
    noise_rounds = True
    warm_refits = True
    monotone = "J"
    history_keys = {
        "trials": "LM trials in this iteration (accepted and rejected)",
        "accepted": "whether a step was accepted",
        "damping": "Marquardt λ after the iteration",
        "lm_status": "the LM driver's RESULTS code for the iteration",
        "smoothing_gain": "J gained by the smoothing check before stopping (0: none tried)",
        "identifiability_checked": "whether the identifiability check formed S in this epoch",
        "identifiability": "None, or what that check found: directions the data do not "
        "determine (Identifiability.to_record(): message, determined, undetermined, eigenvalues, "
        "step_share, stopped)",
    }

    def __check_init__(self):
        for name in ("rho_x", "rho_theta"):
            check_nonnegative(name, getattr(self, name))
        for name in ("check_rtol", "cg_rtol"):
            check_rtol(name, getattr(self, name))
        # λ is relative to the curvature (Marquardt) except in θ with the identity border scaling
        relative = self.border == "dense" or self.border_scaling == "diagonal"
        check_damping("damping", self.damping, self.rtol if relative else 0.0)
        check_positive("max_theta_step", self.max_theta_step, allow_inf=True)  # inf: no bound
        if self.linear_solver not in ("auto", "dense", "cg"):
            raise ValueError(
                f"`linear_solver` must be 'auto', 'dense' or 'cg'; got {self.linear_solver!r}."
            )
        check_int("max_trials", self.max_trials, 1)
        check_int("dense_max_p", self.dense_max_p, 0)
        check_int("cg_max_steps", self.cg_max_steps, 1, none=True)
        check_bool("check_smoothing", self.check_smoothing)
        check_bool("check_identifiability", self.check_identifiability)
        check_choice("border", self.border, ("dense", "matrix-free"))
        check_choice("border_scaling", self.border_scaling, ("diagonal", "identity"))

    def check_problem(self, problem: FitProblem, theta: Theta) -> None:
        """The base class's refusals, and the memory guard, before any compute."""
        super().check_problem(problem, theta)
        system = eqx.combine(problem.template, problem.static)  # θ's shapes: enough for sizes
        B, T = problem.data.y.shape[:2]
        self._check_memory(B, T, system.state_dim, theta.shape[0], theta.dtype.itemsize)

    def _check_memory(self, B: int, T: int, n: int, P: int, itemsize: int) -> None:
        """Refuse arrays that would not fit in memory (:func:`ceemx.infra.memory.check_fits`)."""
        if self.border == "matrix-free":
            # The x-blocks A_b, their damped copy, factors and the LM loop's copies: ≈ 12
            # B·T·n² arrays at the measured peak (6.5 GB at n = 120, B = 16, T = 256), and the
            # factors' inverted diagonal blocks (ceemx.lib.arrowhead.factor).
            check_fits(
                f"JointLM(border='matrix-free')'s x-blocks (≈ 13 arrays of {B} × {T} × {n} × {n})",
                (13 * B * T * n * n + 8 * P) * itemsize,
                "use fewer trajectories, or ceemx.Alternating with LMSmoother(batch_chunk=...) "
                "and a matrix-free learner (ceemx.GaussNewtonCGLearner).",
            )
        else:
            check_fits(
                f"JointLM's linearisation (border E: {B} × {T} × {n} × {P}, θ-Jacobians of the "
                f"same size, {P} × {P} blocks)",
                (3 * B * T * n * P + (B + 4) * P * P) * itemsize,
                "use JointLM(border='matrix-free') (border and Schur complement as "
                "Jacobian-vector products and CG), or ceemx.Alternating with a matrix-free "
                "learner (ceemx.GaussNewtonCGLearner) and, for large n, "
                "LMSmoother(batch_chunk=...).",
            )

    def init(
        self, problem: FitProblem, theta: Theta, states: States, key: PRNGKeyArray
    ) -> FitState:
        """θ, x as given; trajectories non-finite at the start are excluded (with a warning)."""
        B, T, n = states.shape
        self._check_memory(B, T, n, theta.shape[0], states.dtype.itemsize)
        J = trajectory_log_likelihood(problem, theta, states)
        ok = np.isfinite(to_host(J))
        if not ok.all():
            warn(
                f"trajectories {np.flatnonzero(~ok).tolist()} have a non-finite objective at "
                "the initial states; they are excluded from the joint fit."
            )
        return FitState(
            theta=theta,
            states=states,
            J=J,
            weights=jnp.asarray(ok, states.dtype),
            status=select(as_jax(ok), RESULTS.successful, RESULTS.nonfinite),
            solver_state=jnp.asarray(self.damping, states.dtype),
        )

    def precompile(
        self, problem: FitProblem, theta: Theta, states: States
    ) -> tuple[Callable[[], object], ...]:
        """Jobs compiling the joint iteration and the identifiability check's S (nothing runs).

        The arguments are built as :meth:`init` and :meth:`step` build theirs (weights and λ
        of the states' dtype), so the epochs find both programs compiled.
        """

        def iteration() -> None:
            weights = jnp.ones(states.shape[:1], states.dtype)
            lam = jnp.asarray(self.damping, states.dtype)
            _iteration.lower(self, problem, weights, theta, states, lam).compile()

        def check() -> None:
            weights = jnp.ones(states.shape[:1], states.dtype)
            schur.schur_complement.lower(problem, theta, states, weights).compile()

        if self.check_identifiability and theta.shape[0] <= MAX_P:
            return (iteration, check)
        return (iteration,)

    def step(self, problem: FitProblem, state: FitState) -> tuple[FitState, dict]:
        """One accepted LM step on (x, θ) (or the trials that failed to find one)."""
        theta, states, lam, code, n_acc, trials, nll = _iteration(
            self, problem, state.weights, state.theta, state.states, state.solver_state
        )
        accepted = int(n_acc) > 0
        ok = state.weights > 0
        run = RESULTS.successful if accepted else code
        new = FitState(
            theta=theta,
            states=states,
            J=jnp.where(ok, -nll, state.J),
            weights=state.weights,
            status=select(ok, run, RESULTS.nonfinite),
            solver_state=lam,
        )
        record = {
            "trials": int(trials),
            "accepted": accepted,
            "damping": float(lam),
            "lm_status": int(codes(code)),
            "smoothing_gain": 0.0,
            "identifiability_checked": False,
            "identifiability": None,
        }
        stop, _ = self._stopping(problem, state, new, record)
        if not stop and accepted:
            new, checked, found = self._identifiability_check(problem, state, new)
            record["identifiability_checked"] = checked
            if found is not None:
                record["identifiability"] = found.to_record()
                stop = found.stopped
        if stop and self.check_smoothing and np.any(to_host(ok)):
            new, record["smoothing_gain"] = self._smoothing_check(problem, new)
        return new, record

    def _stopping(self, problem, before, after, record) -> tuple[bool, bool]:
        """(stop, converged) by Algorithm 1's rule, the LM's predicted decrease, or stuck."""
        if not np.any(to_host(after.weights) > 0):
            return True, False
        lm_converged = record["lm_status"] == int(codes(RESULTS.successful))
        if record["accepted"]:
            converged = lm_converged or improvement_converged(
                problem, before, after, self.rtol, self.atol
            )
            return converged, converged
        # No accepted step: converged if the model predicted no decrease, else damping exhausted
        # or non-finite trials — stop either way.
        return True, lm_converged

    def _identifiability_check(
        self, problem: FitProblem, before: FitState, after: FitState
    ) -> tuple[FitState, bool, Identifiability | None]:
        """S at ``after`` when J improved immaterially: the first time, and while θ still moves.

        Returns the state (with ``cache`` updated), whether S was formed, and what it showed.

        ``cache`` carries the scaled length of the θ-step and whether a check ran to the next
        epoch (lost on a resume: the next check is then a first one again).
        """
        th0, th1 = np.asarray(before.theta), np.asarray(after.theta)
        step = th1 - th0
        size = float(np.linalg.norm(step / np.maximum(np.abs(th1), 1.0)))
        last = before.cache if isinstance(before.cache, dict) else {"step": None, "checked": False}
        moving = last["step"] is not None and size >= NOT_SHRINKING * float(last["step"])
        due = size > 0.0 and (moving or not last["checked"])
        check = (
            self.check_identifiability
            and due
            and not has_learned_term(problem.build(after.theta))  # weights: never determined
            and th1.size <= MAX_P
            and improvement_converged(problem, before, after, self.check_rtol, 0.0)
        )
        after = dataclasses.replace(
            after, cache={"step": size, "checked": last["checked"] or check}
        )
        found = (
            identifiability_at(problem, after.theta, after.states, after.weights, step)
            if check
            else None
        )
        return after, check, found

    def _smoothing_check(self, problem: FitProblem, state: FitState) -> tuple[FitState, float]:
        """One smoothing pass at the end θ; its states if it raises J materially."""
        ok = to_host(state.weights) > 0
        sol = smoothing_solver.smooth_batch(
            trace_numbers(smoothing_solver.LMSmoother(), state.states.dtype),
            problem.build(state.theta),
            state.states,
            problem.data,
            False,
            Runs.ONCE,  # the warm start's program, when the shapes and noise models agree
        )
        J_new = to_host(trajectory_log_likelihood(problem, state.theta, sol.states))
        J_old = to_host(state.J)
        better = ok & np.isfinite(J_new) & (J_new > J_old)
        gain = float(np.sum(np.where(better, J_new - J_old, 0.0)))
        if not gain > float(self.check_rtol) * objective_scale(problem, state):
            return state, 0.0
        keep = as_jax(better)
        states = jnp.where(keep[:, None, None], sol.states, state.states)
        return (
            FitState(
                theta=state.theta,
                states=states,
                J=jnp.where(keep, jnp.asarray(J_new), state.J),
                weights=state.weights,
                status=state.status,
                solver_state=state.solver_state,
                cache=state.cache,
            ),
            gain,
        )

    def terminate(self, problem, before, after, record):
        """Converged on Algorithm 1's rule or a negligible predicted decrease; stop if stuck.

        Never right after the smoothing check moved the states (the iterations go on from them).
        """
        if record.get("smoothing_gain", 0.0) > 0.0:
            return False, False
        found = record.get("identifiability")
        if found is not None and found["stopped"]:
            return True, True
        return self._stopping(problem, before, after, record)

    def identifiability(self, problem, state, history, converged):
        """The last identifiability check's finding, else :func:`end_point_identifiability`."""
        for record in reversed(history):
            if record.get("identifiability") is not None:
                return Identifiability.from_record(record["identifiability"])
        return end_point_identifiability(problem, state, history, converged)


def _value(problem: FitProblem, weights: PerTrajectory, offset: Scalar):
    """``z = (x, θ) -> value`` of ``schur.joint_evaluator`` without the linearisation (trials)."""
    ok_b = weights > 0

    def value(z):
        x, th = z
        nll = problem.per_trajectory(th, x)
        return jnp.sum(jnp.where(ok_b, nll, 0.0)) - offset + problem.neg_log_prior(th)

    return value


def _iteration_work(opts, problem, weights, theta: Theta, states: States, lam):
    """The joint iteration's work (:func:`ceemx.infra.policy.joint_iteration_work`)."""
    del opts, problem, weights, lam
    B, T, n = states.shape
    return joint_iteration_work(B, T, n, theta.shape[0])


@program(work=_iteration_work)  # every epoch: one-shot on tiny problems only (ceemx.infra.policy)
def _iteration(
    opts: JointLM,
    problem: FitProblem,
    weights: PerTrajectory,
    theta: Theta,
    states: States,
    lam: Scalar,
):
    """One accepted LM step on (x, θ): linearise at (x, θ), try steps until one is accepted.

    Trial points are judged by their value alone (the LM driver's lazy mode), so a rejected trial
    costs one objective evaluation, and the compiled program holds one linearisation.

    Returns (θ, x, λ, status, accepted steps, trials, −J_b at the new point).
    """
    if opts.border == "matrix-free":
        return joint_matrix_free.iteration(opts, problem, weights, theta, states, lam)
    ok_b = weights > 0
    dtype = states.dtype
    rho_x = jnp.asarray(opts.rho_x, dtype)
    rho_t = jnp.asarray(opts.rho_theta, dtype)
    max_step = jnp.asarray(opts.max_theta_step, dtype)
    offset = problem.offset(theta, weights)
    evaluate = schur.joint_evaluator(problem, weights, offset)

    def grad_of(lin):
        return (lin.grad_x, lin.grad_theta)

    def solve(lin, lam):
        dA = jnp.diagonal(lin.A.diagonal, axis1=-2, axis2=-1)
        A_d = lib.add_to_diagonal(lin.A, marquardt_scale(dA, lam) + 2.0 * rho_x)
        D_d = lin.D + jnp.diag(marquardt_scale(jnp.diagonal(lin.D), lam) + 2.0 * rho_t)
        sol = lib.arrowhead_solve(
            A_d,
            lin.E,
            D_d,
            -lin.grad_x,
            -lin.grad_theta,
            method=opts.linear_solver,
            dense_max_p=opts.dense_max_p,
            cg_rtol=opts.cg_rtol,
            cg_max_steps=opts.cg_max_steps,
        )
        dx = jnp.where(ok_b[:, None, None], sol.dx, 0.0)
        # Trust region in scaled variables: shorten (δx, δθ) so no θ_i moves by more than
        # max_theta_step·max(|θ_i|, 1).
        ratio = jnp.max(jnp.abs(sol.dtheta) / jnp.maximum(jnp.abs(theta), 1.0), initial=0.0)
        shrink = jnp.minimum(1.0, max_step / jnp.maximum(ratio, jnp.finfo(dtype).tiny))
        return (shrink * dx, shrink * sol.dtheta), sol.ok

    def quad(lin, delta):
        dx, dth = delta
        xAx = jnp.sum(dx * jax.vmap(lib.matvec)(lin.A, dx))
        xEt = jnp.einsum("btn,btnp,p->", dx, lin.E, dth)
        prox = rho_x * jnp.sum(dx**2) + rho_t * jnp.sum(dth**2)
        return xAx + 2.0 * xEt + dth @ lin.D @ dth + 2.0 * prox

    out = levenberg_marquardt(
        evaluate,
        grad_of,
        solve,
        quad,
        (states, theta),
        rtol=opts.rtol,
        atol=0.0,
        max_steps=opts.max_trials,
        damping=lam,
        max_accepted=1,
        value=_value(problem, weights, offset),
    )
    x, th = out.z
    nll = problem.per_trajectory(th, x)
    return th, x, out.damping, out.status, out.accepted, out.steps, nll
