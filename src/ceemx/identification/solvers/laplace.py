"""Laplace (MAP-) EM: beyond certainty equivalence, with learned noise covariances.

CE-EM maximises J(x, θ) = log p(x, y | θ) jointly, which ignores the spread of the state posterior:
it biases θ under process noise and is unbounded in the noise scales (J → ∞ as σ → 0 when the
states absorb the residuals), so σ_w and σ_v cannot be learned. Laplace EM (the MAP-EM of Goodwin
& Agüero 2005, named in the paper's conclusion) is EM with a Gaussian E-step:

- **E-step** at θᵏ: the MAP trajectory x̂ of each trajectory (the CE-EM smoother, Eq. 10) and the
  Laplace approximation q = N(x̂, Σ̂), Σ̂ the inverse Gauss–Newton matrix of −J at x̂ — its marginal
  blocks Σ̂_t and lag-one blocks Cov(x_{t+1}, x_t) from the selected inverse of the same
  block-tridiagonal factorisation (O(T n³)).
- **M-step**: θᵏ⁺¹ maximises Q(θ) = E_q[log p(x, y | θ)] (− log-prior, + trust region ρ_θ), the
  expectations by cubature over the marginals and the pairwise marginals
  (:mod:`ceemx.identification.learning.expected`), by any learner; then, for Gaussian noise models
  whose leaves
  are trainable, the noise covariances in closed form from the expected residual second moments at
  θᵏ⁺¹ (an ECM step: for a model linear in its parameters with unrestricted matrices this is the
  exact joint M-step).

On a linear-Gaussian model q is the exact posterior and the rule integrates the quadratic terms
exactly, so the method is exact EM (tested against a Kalman/RTS EM to 1e-8 per iteration). The
objective tracked is the Laplace approximation of the marginal log-likelihood
log p(y | θ) ≈ J(x̂, θ) + (Tn/2) log 2π − ½ log det H (exact for linear-Gaussian models), in the
history as ``log_evidence``; the fit stops when it changes by at most ``rtol·|J + c| + atol``,
and, not converged, at the first epoch that lowers it by more: EM climbs the evidence where its
E-step is exact, and a fall means its fixed point lies past the evidence's maximum (a model
curved in the state), so that epoch is discarded and the better point kept.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PRNGKeyArray

from ceemx.identification.learning import learners as _learners
from ceemx.identification.learning import step as learning_step
from ceemx.identification.learning.expected import ExpectedLearningProblem, cubature_points
from ceemx.identification.noise_moments import (
    COARSE_STEPS,
    NOISE_FIELDS,
    coarse_shape,
    noise_second_moments,
    updated_noise,
)
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import (
    AbstractFitSolver,
    FitState,
    check_alternation,
    objective_scale,
    participating_sum,
    trajectory_log_likelihood,
)
from ceemx.identification.solvers.laplace_newton import newton_polish
from ceemx.identification.solvers.laplace_qn import (
    QN_BACKTRACKS,
    QN_EXPAND,
    QN_MAX_PARAMETERS,
    QN_MAX_STEP,
    Coordinates,
    bfgs_update,
    log_prior_value,
    qn_gradient,
    qn_start,
)
from ceemx.inference import smoother as smoothing_solver
from ceemx.inference.posterior import E_STEP_SMOOTHER, GaussianPosterior, gaussian_posterior
from ceemx.infra.distributed import to_host
from ceemx.infra.options import check_choice, check_int
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, codes
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import PerTrajectory, States, Theta
from ceemx.models.system import AbstractSystem

__all__ = ["COARSE_MAX_EPOCHS", "LaplaceEM"]


#: the most epochs the coarse start's fit takes
COARSE_MAX_EPOCHS = 100


def _check_learned_noise(problem: FitProblem, system: AbstractSystem) -> tuple[str, ...]:
    learned = tuple(f for f in NOISE_FIELDS if problem.trains(f))
    for field in learned:
        noise = getattr(system, field)
        if not noise.learnable_in_closed_form:
            raise ValueError(
                f"`trainable` selects `system.{field}`, a {type(noise).__name__}: LaplaceEM "
                "learns noise covariances in closed form, for noise models that have one "
                "(`learnable_in_closed_form`: DiagonalGaussian or CholeskyGaussian) only."
            )
    return learned


class LaplaceEM(AbstractFitSolver):
    """Laplace (MAP-) EM: Gaussian E-step around the MAP trajectory, cubature M-step (module docs).

    Learns noise covariances: select the noise models' leaves in ``fit(trainable=...)`` (e.g.
    ``lambda s: (s.sigma, s.process_noise, s.obs_noise)``, or every model parameter and the noise:
    ``ceemx.identification.problem.trainable_mask(model, noise=True)``); DiagonalGaussian scales
    (scalar or
    per component) and CholeskyGaussian factors are updated in closed form each epoch. Only this
    solver accepts trainable noise: the CE-EM objective is unbounded in the noise scales.

    Attributes:
        smoother: the E-step's MAP smoother (default ``LMSmoother(rtol=1e-14, damping=1e-6)``:
            the posterior is evaluated at its answer; its ``rho_x`` should stay 0, since a trust
            region towards the previous states would move the MAP; the previous states are its
            start, hence the small initial damping).
        learner: the M-step's optimiser over the non-noise θ (default Levenberg–Marquardt, run to
            convergence so the M-step is exact on models linear in θ).
        rho_theta: ρ_θ ≥ 0, a trust region on the M-step's θ (0: plain EM).
        acceleration: ``"squarem"`` (default): each epoch is one SQUAREM cycle (Varadhan &
            Roland 2008) — two EM updates θ₁ = M(θ₀), θ₂ = M(θ₁), the extrapolation
            θ' = θ₀ − 2αr + α²v (r = θ₁ − θ₀, v = θ₂ − 2θ₁ + θ₀, α = min(−‖r‖/‖v‖, −1)) and one
            stabilising update M(θ'), kept only when its log-evidence is at least θ₂'s (so an
            epoch never does worse than two EM updates). EM creeps when the missing information
            is large — small process noise, learned noise — and SQUAREM cuts the epochs by an
            order of magnitude there. ``"quasi_newton"``: each epoch is one quasi-Newton step on
            the EM fixed-point equation ∇Q(θ | θ) = 0 (Jamshidian & Jennrich 1997): the
            ascent direction of the Laplace log-evidence (+ log-prior) from the gradient of Q at
            θ (Fisher's identity; exact on models linear in the state), BFGS curvature started
            from the complete-data information −∇²Q (EM's own metric, so the first step is
            EM's), log-coordinates for DiagonalGaussian noise scales, an Armijo backtracking on
            the log-evidence and a plain EM update when that fails. An epoch costs one E-step
            and one gradient of Q (no M-step optimisation) and the steps learn the missing
            information EM creeps along; the learner and ``rho_theta`` are not used. For small
            θ (≤ ``QN_MAX_PARAMETERS`` entries: the curvature is a dense P × P Hessian) and
            models linear in the state, where its gradient is the evidence's (on nonlinear
            models it can take many more epochs than SQUAREM and stop below its evidence).
            ``None``: one plain EM update per epoch (exact EM).
        rtol, atol: stop when the Laplace log-evidence changes by at most ``rtol·|J + c| + atol``
            in an epoch; an epoch that lowers it by more is discarded and the fit stops there,
            not converged.
        polish: after the epochs, test the end point on the Laplace evidence itself — its
            gradient and Hessian by finite differences — and take up to three Newton steps to
            its maximum (:mod:`~ceemx.identification.solvers.laplace_newton`); ``converged`` is
            then the test's verdict where the evidence's Hessian is negative definite. For θ of
            at most ``POLISH_MAX_PARAMETERS`` entries (each test costs 2P² + 2P + 1
            smoothings). Where the model is curved in the state, EM's fixed point is not the
            evidence's maximum, and no change-per-epoch rule tells the two apart.
        coarse_start: long data start from a fit on part of them. When the data hold at least
            ``COARSE_FACTOR`` (4) × ``coarse_start`` time steps (B·T), this solver first fits
            about ``coarse_start`` of them — the first b = ⌈coarse_start / T⌉ trajectories, each
            cut to its first ⌈coarse_start / b⌉ steps — with the same options and tolerances (at
            most ``COARSE_MAX_EPOCHS`` epochs), and its θ starts the fit on all the data when it
            converged and the Laplace log-evidence (+ log-prior) of all the data is there at
            least the given start's (else the given start stands). With
            ``acceleration="quasi_newton"`` the coarse fit's BFGS curvature, scaled by the ratio
            of the two sizes (the evidence's Hessian grows with the data), starts the curvature:
            the epochs on all the data are then Newton-like from the first, where EM's metric
            needs many to learn the missing information.
            ``None``: never. Epoch 1's history record says what it did (``coarse_*``).
    """

    smoother: smoothing_solver.LMSmoother = eqx.field(default_factory=lambda: E_STEP_SMOOTHER)
    learner: _learners.AbstractLearner = eqx.field(default_factory=_learners.LMLearner)
    rho_theta: float = 0.0
    acceleration: str | None = eqx.field(default="squarem", static=True)
    rtol: float = 1e-10
    atol: float = 0.0
    coarse_start: int | None = eqx.field(default=COARSE_STEPS, static=True)
    polish: bool = eqx.field(default=False, static=True)

    learns_noise: ClassVar[bool] = True
    uncertainty = "evidence"
    monotone = "log_evidence"
    history_keys = {
        "log_evidence": "Laplace approximation of Σ_b log p(y_b | θ) at the epoch's θ",
        "Q_gain": "increase of Q(θ) = E_q[log p(x, y | θ)] in the M-step (≥ 0 up to round-off)",
        "smooth_time": "seconds in the E-step (MAP smoothing and selected inverse)",
        "learn_time": "seconds in the M-step",
        "smoother_steps": "most LM iterations any trajectory took in the E-step",
        "learner_steps": "iterations of the M-step's learner",
        "learner_status": "the M-step learner's RESULTS code",
        "squarem_alpha": "SQUAREM step length α of the epoch (None: plain EM updates were kept)",
        "qn_step": "quasi-Newton step length kept (None: the line search failed, an EM update)",
        "process_noise_std": "learned process-noise standard deviations (when trainable)",
        "obs_noise_std": "learned observation-noise standard deviations (when trainable)",
        "coarse_steps": "epoch 1 only: time steps of the coarse start's data (``coarse_start``)",
        "coarse_epochs": "epoch 1 only: epochs of the coarse start's fit",
        "coarse_converged": "epoch 1 only: whether the coarse start's fit converged",
        "coarse_time": "epoch 1 only: seconds in the coarse start (its fit and the check)",
        "coarse_used": "epoch 1 only: whether the coarse fit's θ started the fit",
        "evidence_fell": "nats the epoch's updates lowered the log-evidence by, beyond the "
        "tolerance: they were discarded (the epoch's θ is the previous one) and the fit stopped",
        "newton_steps": "the polish's record only (``polish``): Newton steps kept",
        "newton_decrements": "the polish's Newton decrements ½ gᵀ(−H)⁻¹g, one per test (nats)",
        "newton_gain": "the polish's rise of the log-evidence (+ log-prior), nats",
        "newton_result": "the polish's verdict in words",
    }

    def __check_init__(self):
        check_choice("acceleration", self.acceleration, ("squarem", "quasi_newton", None))
        check_int("coarse_start", self.coarse_start, 2, none=True)
        check_alternation(self.smoother, self.learner, self.rho_theta)

    def _posterior(
        self, problem: FitProblem, theta: Theta, x0: States, *, quiet: bool = False
    ) -> GaussianPosterior:
        e = gaussian_posterior(self.smoother, problem.build(theta), x0, problem.data)
        failed = np.asarray(e.status == RESULTS.nonfinite)
        if failed.any() and not quiet:
            warn(
                f"the E-step failed (non-finite objective or covariance) on trajectories "
                f"{np.flatnonzero(failed).tolist()}; they are excluded from the M-step."
            )
        return e

    def _state(
        self, problem: FitProblem, theta: Theta, e: GaussianPosterior, start: States, learner_state
    ) -> FitState:
        """The fit state of posteriors ``e`` at θ, smoothed from ``start``.

        ``solver_state`` is (learner state, log-evidence, ``start``): the smoother's start is
        checkpointed so that a resume recomputes ``e`` — the ``cache`` — from the very inputs
        that gave it, bit for bit. (Recomputed from ``e.states``, the states it converged to, a
        resume ended ≈ 1e-10 away from the uninterrupted run.)
        """
        return FitState(
            theta=theta,
            states=e.states,
            J=trajectory_log_likelihood(problem, theta, e.states),
            weights=_weights(e),
            status=e.status,
            solver_state=(learner_state, e.log_evidence, start),
            cache=e,
        )

    def check_problem(self, problem: FitProblem, theta: Theta) -> None:
        """Learned noise models must be Gaussian (their M-step is closed-form).

        And the learner's memory guard, before any compute.
        """
        _check_learned_noise(problem, problem.build(theta))
        self.learner.check_memory(theta.shape[0], problem.data.batch_size, theta.dtype.itemsize)

    def init(
        self, problem: FitProblem, theta: Theta, states: States, key: PRNGKeyArray
    ) -> FitState:
        """The E-step at the initial θ from the given states; the learner's state from ``key``.

        On long data, first the coarse start (``coarse_start``): the E-step is then at the
        coarse fit's θ when it has the larger evidence.
        """
        _check_learned_noise(problem, problem.build(theta))
        qn = self.acceleration == "quasi_newton"
        if qn and theta.shape[0] > QN_MAX_PARAMETERS:
            raise ValueError(
                f"`acceleration='quasi_newton'` keeps a dense P × P curvature: θ has "
                f"{theta.shape[0]} entries (at most {QN_MAX_PARAMETERS}); use 'squarem'."
            )
        e = self._posterior(problem, theta, states)
        learner_state = self.learner.init(theta, key)
        coarse = self._coarse_start(problem, theta, e, key)
        record: dict[str, Any] = {}
        curvature = None
        if coarse is not None:
            theta, e, curvature, record = coarse
        if qn:
            if curvature is None:
                learner_state = (learner_state, *qn_start(problem, theta, e))
            else:
                learner_state = (learner_state, curvature, qn_gradient(problem, theta, e))
        state = self._state(problem, theta, e, states, learner_state)
        return dataclasses.replace(state, cache=(e, record)) if record else state

    def _coarse_start(self, problem: FitProblem, theta: Theta, e: GaussianPosterior, key):
        """The coarse start (``coarse_start``): ``None`` when the data are short.

        Else (θ, posteriors at θ, curvature or ``None``, epoch-1 record): the coarse fit's θ
        when the evidence (+ log-prior) of all the data is there at least the start's (``e``
        at ``theta``), else ``theta`` and ``e`` as given. Warnings of the coarse fit are not
        shown (its failures fall back on the given start).
        """
        B, T = e.states.shape[:2]
        shape = coarse_shape(B, T, self.coarse_start)
        if shape is None:
            return None
        t0 = time.perf_counter()
        b, t = shape
        sub = eqx.tree_at(lambda p: p.data, problem, problem.data[:b].head(t))
        # the part holds fewer than COARSE_FACTOR·coarse_start steps: its fit starts no coarse
        # fit of its own (and the solver's numbers stay the traced arrays the driver made)
        solver = self
        epochs, converged, curvature, e_c = 0, False, None, None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            state = solver.init(sub, theta, e.states[:b, :t], key)
            stop = False
            while epochs < COARSE_MAX_EPOCHS and not stop:
                new, rec = solver.step(sub, state)
                stop, converged = solver.terminate(sub, state, new, rec)
                state, epochs = new, epochs + 1
            # only a converged coarse fit: one that is not is no estimate (too few data for θ:
            # a near-singular noise covariance, met on 40 samples of a 10-parameter model)
            theta_c = state.theta
            if converged and _valid(problem, theta_c):
                e_c = self._posterior(problem, theta_c, e.states, quiet=True)
        record = {
            "coarse_steps": b * t,
            "coarse_epochs": epochs,
            "coarse_converged": converged,
            "coarse_used": False,
        }
        if e_c is not None and bool(jnp.all(e_c.status != RESULTS.nonfinite)):
            f0 = participating_sum(e.log_evidence, 1.0) + log_prior_value(problem, theta)
            f0 = f0 if np.isfinite(f0) else -np.inf  # a failed start: any finite fit is better
            f_c = participating_sum(e_c.log_evidence, 1.0) + log_prior_value(problem, theta_c)
            if np.isfinite(f_c) and f_c >= f0:
                record["coarse_used"] = True
                theta, e = theta_c, e_c
                if self.acceleration == "quasi_newton":
                    curvature = state.solver_state[0][1] * ((b * t) / (B * T))
        record["coarse_time"] = time.perf_counter() - t0
        return theta, e, curvature, record

    def _em_update(
        self, problem: FitProblem, theta: Theta, e: GaussianPosterior, learner_state, record: dict
    ) -> tuple[Theta, Any, GaussianPosterior]:
        """One EM update θ → M(θ): the M-step from the posteriors ``e`` at θ, then the E-step.

        The E-step smooths from ``e.states`` (the start to checkpoint with its answer).
        """
        weights = _weights(e)
        t0 = time.perf_counter()
        split = _NoiseSplit(problem, theta)
        points, pairs = cubature_points(e.states, e.covariances, e.cross)
        theta_inner = split.theta_inner
        system = problem.build(theta)
        if split.inner is not None and theta_inner is not None:
            mp = ExpectedLearningProblem(
                problem=split.inner,
                points=points,
                pairs=pairs,
                weights=weights,
                theta_ref=theta_inner,
                rho_theta=jnp.asarray(self.rho_theta, theta.dtype),
            )
            theta_inner, learner_state, info = learning_step.run_learner(
                self.learner, mp, theta_inner, learner_state
            )
            theta_inner.block_until_ready()
            system = split.inner.build(theta_inner)
            record["Q_gain"] += float(info.value_before) - float(info.value_after)
            record["learner_steps"] += int(info.steps)
            record["learner_status"] = max(record["learner_status"], int(codes(info.status)))
        if split.learned:
            moments = noise_second_moments(system, points, pairs, problem.data, weights)
            for field in split.learned:
                noise = updated_noise(getattr(system, field), field, moments)
                system = eqx.tree_at(lambda s, f=field: getattr(s, f), system, replace=noise)
        theta_new = split.join(theta_inner, system).astype(theta.dtype)
        record["learn_time"] += time.perf_counter() - t0
        e_new = self._timed_posterior(problem, theta_new, e.states, record)
        return theta_new, learner_state, e_new

    def _timed_posterior(self, problem, theta, x0, record, quiet=False) -> GaussianPosterior:
        t0 = time.perf_counter()
        e = self._posterior(problem, theta, x0, quiet=quiet)
        record["smooth_time"] += time.perf_counter() - t0
        record["smoother_steps"] = max(record["smoother_steps"], int(np.max(to_host(e.iterations))))
        return e

    def step(self, problem: FitProblem, state: FitState) -> tuple[FitState, dict]:
        """One EM update (M-step, then E-step), or one SQUAREM cycle of three."""
        learner_state, _, start = state.solver_state
        record: dict[str, Any] = {
            "Q_gain": 0.0,
            "smooth_time": 0.0,
            "learn_time": 0.0,
            "smoother_steps": 0,
            "learner_steps": 0,
            "learner_status": int(codes(RESULTS.successful)),
        }
        e0 = state.cache
        if isinstance(e0, tuple):  # the first epoch after a coarse start: its record
            e0, start_record = e0
            record.update(start_record)
        if e0 is None:  # resumed from a checkpoint: the posteriors at θ, from the saved start
            # (as computed before the checkpoint; not counted in this epoch's record)
            e0 = self._posterior(problem, state.theta, start, quiet=True)
        new, record = self._advance(problem, state, e0, learner_state, start, record)
        # EM climbs the evidence; an epoch that lowers it beyond the tolerance has passed EM's
        # fixed point beyond the evidence's maximum (the E-step inexact: a model curved in the
        # state): the previous point is the better one, and the fit stops there
        before = participating_sum(state.solver_state[1], new.weights)
        after = record["log_evidence"]
        tol = float(self.rtol) * objective_scale(problem, state) + float(self.atol)
        if np.isfinite(before) and np.isfinite(after) and after < before - tol:
            record["evidence_fell"] = before - after
            record["log_evidence"] = before
            return dataclasses.replace(state, cache=e0), record
        return new, record

    def _advance(self, problem, state, e0, learner_state, start, record):
        """The epoch's updates from the posteriors ``e0`` at ``state.theta``."""
        if self.acceleration == "quasi_newton":
            return self._qn_step(problem, state, e0, learner_state, record)
        th0 = state.theta
        th1, learner_state, e1 = self._em_update(problem, th0, e0, learner_state, record)
        theta, e, start = th1, e1, e0.states
        if self.acceleration == "squarem":
            th2, learner_state, e2 = self._em_update(problem, th1, e1, learner_state, record)
            theta, e, start = th2, e2, e1.states
            extrapolated = self._extrapolate(problem, th0, th1, th2, e2, learner_state, record)
            record["squarem_alpha"] = None if extrapolated is None else extrapolated[0]
            if extrapolated is not None:
                _, theta, e, learner_state, start = extrapolated
        return self._finish(problem, theta, e, start, learner_state, record)

    def _finish(self, problem, theta, e, start, learner_state, record):
        new = self._state(problem, theta, e, start, learner_state)
        system = problem.build(theta)
        for field in NOISE_FIELDS:
            if problem.trains(field):
                cov = np.asarray(getattr(system, field).covariance())
                record[f"{field}_std"] = np.sqrt(np.diagonal(cov)).tolist()
        record["log_evidence"] = participating_sum(e.log_evidence, new.weights)
        return new, record

    def _qn_step(self, problem, state, e0, memory, record):
        """One quasi-Newton step on ∇Q(θ | θ) = 0 (``acceleration="quasi_newton"``).

        ``memory`` is (learner state, inverse curvature H⁻¹ in z, ascent gradient g in z at θ).
        Direction d = H⁻¹g (no entry beyond ``QN_MAX_STEP`` in z), step lengths 1, ¼, 1/16, …
        until the log-evidence (+ log-prior) rises by Armijo's 10⁻⁴·s·gᵀd; then BFGS on the
        change of g. When no step is accepted: one plain EM update, the curvature restarted.
        """
        learner_state, Hinv, g = memory
        Hinv, g = np.asarray(Hinv), np.asarray(g)
        t0 = time.perf_counter()
        coords = Coordinates(problem, state.theta)
        z = coords.z(state.theta)
        f0 = participating_sum(e0.log_evidence, _weights(e0)) + log_prior_value(
            problem, state.theta
        )
        d = Hinv @ g
        big = float(np.max(np.abs(d))) if d.size else 0.0
        if big > QN_MAX_STEP:
            d, big = d * (QN_MAX_STEP / big), QN_MAX_STEP
        slope = float(g @ d)
        record["learn_time"] += time.perf_counter() - t0

        def trial(step):
            theta_t = coords.theta(z + step * d)
            if not _valid(problem, theta_t):
                return None
            e_t = self._timed_posterior(problem, theta_t, e0.states, record, quiet=True)
            if not bool(jnp.all(e_t.status != RESULTS.nonfinite)):
                return None
            return (
                participating_sum(e_t.log_evidence, 1.0) + log_prior_value(problem, theta_t),
                theta_t,
                e_t,
            )

        step, accepted = 1.0, None
        if slope > 0 and np.all(np.isfinite(d)):
            for _ in range(QN_BACKTRACKS):
                got = trial(step)
                if got is not None and got[0] >= f0 + 1e-4 * step * slope:
                    accepted = got
                    break
                step *= 0.25
            # the full step rose as its linear prediction says (no curvature felt): EM's metric
            # underestimates the step here (a ridge, or where BFGS has no curvature yet); double
            # it while the evidence keeps rising that way
            while (
                accepted is not None
                and step < QN_EXPAND
                and accepted[0] - f0 >= 0.75 * step * slope
                and 2 * step * big <= QN_MAX_STEP
            ):
                got = trial(2 * step)
                if got is None or got[0] <= accepted[0]:
                    break
                step, accepted = 2 * step, got
        t0 = time.perf_counter()
        if accepted is None:
            record["qn_step"] = None
            record["learn_time"] += time.perf_counter() - t0
            theta, learner_state, e = self._em_update(
                problem, state.theta, e0, learner_state, record
            )
            Hinv, g = qn_start(problem, theta, e)
        else:
            record["qn_step"] = step
            _, theta, e = accepted
            g_new = np.asarray(qn_gradient(problem, theta, e), float)
            Hinv = bfgs_update(Hinv, Coordinates(problem, theta).z(theta) - z, g - g_new)
            g = g_new
            record["learn_time"] += time.perf_counter() - t0
        dtype = state.theta.dtype
        memory = (learner_state, jnp.asarray(Hinv, dtype), jnp.asarray(g, dtype))
        return self._finish(problem, theta, e, e0.states, memory, record)

    def _extrapolate(self, problem, th0, th1, th2, e2, learner_state, record):
        """SQUAREM's step from θ₀ through M(θ₀), M(M(θ₀)), stabilised by one more EM update.

        Returns (α, θ, posteriors, learner state, the posteriors' smoother start), or ``None``
        when the extrapolated point is invalid (a noise scale crossed zero, a posterior is not
        finite) or its stabilised update has less evidence than θ₂ — then the two plain updates
        stand.
        """
        # the step on the host in NumPy (op by op, JAX compiled a program per shape)
        h0, h1, h2 = (np.asarray(t) for t in (th0, th1, th2))
        r = h1 - h0
        v = h2 - h1 - r
        nv = float(np.linalg.norm(v))
        if not (nv > 0 and np.isfinite(nv)):
            return None
        alpha = min(-float(np.linalg.norm(r)) / nv, -1.0)
        th_x = as_jax(h0 - 2.0 * alpha * r + alpha**2 * v)
        if not _valid(problem, th_x):
            return None
        e_x = self._timed_posterior(problem, th_x, e2.states, record, quiet=True)
        if not bool(jnp.all(e_x.status != RESULTS.nonfinite)):
            return None
        th3, ls3, e3 = self._em_update(problem, th_x, e_x, learner_state, record)
        if participating_sum(e3.log_evidence, 1.0) < participating_sum(e2.log_evidence, 1.0):
            return None
        return alpha, th3, e3, ls3, e_x.states

    def end_check(
        self, problem: FitProblem, state: FitState
    ) -> tuple[FitState, bool | None, dict[str, Any]]:
        """With ``polish``: Newton's check and polish on the evidence (:func:`newton_polish`)."""
        if not self.polish:
            return state, None, {}
        return newton_polish(self, problem, state)

    def terminate(
        self, problem: FitProblem, before: FitState, after: FitState, record: dict[str, Any]
    ) -> tuple[bool, bool]:
        """Stop when the Laplace log-evidence changes by at most ``rtol·|J + c| + atol``.

        Stop, not converged, after an epoch ``step`` discarded for lowering it by more.
        """
        if not np.any(np.asarray(after.weights) > 0):
            return True, False
        ev_before = participating_sum(before.solver_state[1], after.weights)
        ev_after = participating_sum(after.solver_state[1], after.weights)
        if not np.isfinite(ev_after):
            return False, False
        if "evidence_fell" in record:  # the epoch was discarded (``step``): stop, unproven
            return True, False
        tol = float(self.rtol) * objective_scale(problem, after) + float(self.atol)
        converged = bool(abs(ev_after - ev_before) <= tol)
        return converged, converged


def _valid(problem: FitProblem, theta: Theta) -> bool:
    """Whether θ builds a system with valid noise (an extrapolated scale may cross zero)."""
    if not np.all(np.isfinite(np.asarray(theta))):
        return False
    system = problem.build(theta)
    try:
        system.check()
    except ValueError:
        return False
    return True


def _weights(e: GaussianPosterior) -> PerTrajectory:
    """(B,) 1 where the E-step succeeded, 0 where it failed (excluded from the M-step)."""
    return jnp.where(e.status == RESULTS.nonfinite, 0.0, 1.0).astype(e.states.dtype)


class _NoiseSplit:
    """θ split into the model part (learned by the M-step's learner) and the learned noise leaves.

    Built from the problem's template in *unconstrained* coordinates: the model part keeps its
    values as they are (never mapped to natural units and back, which would send a parameter
    saturated at a bound to ±∞), and the noise leaves — unconstrained, so natural — are fixed in
    the inner problem's static part at their current values.
    """

    def __init__(self, problem: FitProblem, theta: Theta):
        self.problem = problem
        self.theta = theta
        learned = tuple(f for f in NOISE_FIELDS if problem.trains(f))
        self.learned = learned
        _, self.unravel = ravel_pytree(problem.template)
        if not learned:
            self.inner, self.theta_inner, self.marks = problem, theta, None
            return
        marks = jtu.tree_map(lambda _: False, problem.template)
        for f in learned:
            sub = jtu.tree_map(lambda _: True, getattr(marks, f))
            marks = eqx.tree_at(lambda s, f=f: getattr(s, f), marks, replace=sub)
        self.marks = jtu.tree_leaves(marks)
        params = self.unravel(theta)
        model = jtu.tree_map(lambda x, m: None if m else x, params, marks)
        if not jtu.tree_leaves(model):  # only noise is learned
            self.inner, self.theta_inner = None, None
            return
        noise = jtu.tree_map(lambda x, m: x if m else None, params, marks)
        constraints = tuple(
            c for c, m in zip(problem.constraints, self.marks, strict=True) if not m
        )
        self.inner = FitProblem(
            model,
            eqx.combine(noise, problem.static),
            problem.data,
            problem.log_prior,
            constraints,
            problem.overrides,
        )
        self.theta_inner = ravel_pytree(model)[0]

    def join(self, theta_inner: Array | None, system: AbstractSystem) -> Theta:
        """The full θ: the model part from ``theta_inner``, the noise leaves from ``system``."""
        if self.marks is None:
            assert theta_inner is not None
            return theta_inner
        template = self.problem.template
        mask = jtu.tree_map(lambda v: v is not None, template, is_leaf=lambda v: v is None)
        natural = jtu.tree_leaves(eqx.filter(system, mask))
        old = jtu.tree_leaves(self.unravel(self.theta))
        model: list = []
        if self.inner is not None and theta_inner is not None:
            model = jtu.tree_leaves(ravel_pytree(self.inner.template)[1](theta_inner))
        model_leaves = iter(model)
        out = [
            jnp.asarray(nat, o.dtype).reshape(o.shape) if m else next(model_leaves)
            for o, nat, m in zip(old, natural, self.marks, strict=True)
        ]
        return jnp.concatenate([jnp.ravel(a) for a in out]) if out else self.theta
