"""Particle EM: particle-filter / FFBSi E-step and a Stochastic Approximation EM M-step (SAEM).

The paper's baseline (§4.1.2, after Delyon et al. 1999; Lindsten & Schön 2013): each epoch k

1. filters every trajectory with N particles at θₖ (fully adapted when the system allows it,
   :func:`ceemx.particle_filter`) and draws S smoothed trajectories x⁽ʲ⁾ by FFBSi;
2. updates the stochastic approximation of the EM objective,
   Q̂ₖ(θ) = (1 − γₖ) Q̂ₖ₋₁(θ) + γₖ · (1/S) Σⱼ log p(x⁽ʲ⁾, y | θ);
3. sets θₖ₊₁ = argmax Q̂ₖ(θ) + log p(θ) − ρ_θ‖θ − θₖ‖² with any ceemx learner.

**What is stored, and why.** A general nonlinear model has no finite sufficient statistics, so
Q̂ₖ is kept as a weighted sum over the stored samples themselves: the last ``memory`` epochs'
draws, each with its exact SAEM weight γ_j Π_{i>j}(1 − γ_i). Older draws are dropped; the
weights of the kept ones are renormalised to sum to one, and the history reports the mass that
was kept (``saem_mass``; 1 means Q̂ is exact). With the defaults (α = 0.7, memory 10) the kept
mass falls to ≈ 0.5 by epoch 50 (Figure 2), so late M-steps average about the last ``memory``
epochs' draws; set ``memory`` to ``max_epochs`` for the exact recursion (the M-step's cost grows
linearly with ``memory``).

**Step sizes.** γₖ = 1 for k ≤ ``burn_in`` (plain Monte Carlo EM on the newest draws), then
γₖ = (k − burn_in)^(−α) with 0.5 < α ≤ 1 (Σγ = ∞, Σγ² < ∞: the conditions of Delyon et al.).

The objective is stochastic, so J does not decide convergence: the fit runs ``max_epochs``
unless ``rtol``/``atol`` > 0 ask to stop once ‖θₖ₊₁ − θₖ‖ ≤ rtol·‖θₖ₊₁‖ + atol after the burn-in.
"""

from __future__ import annotations

import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, PyTree

from ceemx.identification.learning import learners as _learners
from ceemx.identification.learning.learning_problem import LearningProblem
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import (
    AbstractFitSolver,
    FitState,
    starting_state,
    trajectory_log_likelihood,
)
from ceemx.inference.particle import (
    check_int,
    check_proposal,
    check_threshold,
    ffbsi_batch,
    filter_batch,
    initial_prior,
    resolve_proposal,
)
from ceemx.infra.compilation import jit
from ceemx.infra.distributed import to_host
from ceemx.infra.options import check_nonnegative, check_real
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, codes, select
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import Scalar, States, Theta
from ceemx.models.system import GaussianPrior

__all__ = ["ParticleEM", "SAEMState", "saem_step_size"]


class SAEMState(eqx.Module):
    """Particle EM's persistent state (checkpointed with the fit).

    Attributes:
        key: the PRNG key of the next epoch (a resumed fit draws what it would have drawn).
        epoch: epochs done.
        samples: (M, B, S, T, n) the stored FFBSi draws of the last M epochs (ring buffer).
        saem_weights: (M,) the SAEM weight of each stored epoch (0: empty slot).
        valid: (M, B) whether each stored draw is finite (its filter succeeded).
        learner_state: the learner's persistent state.
    """

    key: PRNGKeyArray
    epoch: Int[Array, ""]
    samples: Float[Array, "M B S T n"]
    saem_weights: Float[Array, " M"]
    valid: Bool[Array, "M B"]
    learner_state: PyTree


def saem_step_size(epoch, burn_in, alpha):
    """γ_k: 1 for k ≤ burn_in, then (k − burn_in)^(−α) (k: the 1-based epoch)."""
    k = jnp.asarray(epoch)
    after = jnp.maximum(k - burn_in, 1).astype(jnp.result_type(alpha, float))
    return jnp.where(k <= burn_in, jnp.ones_like(after), after ** (-alpha))


class ParticleEM(AbstractFitSolver):
    """Particle EM with FFBSi and SAEM (the paper's §4.1.2 baseline) as a ceemx fit solver.

    Works on any system whose process noise can be sampled and whose initial state has a proper
    prior (``initial`` or the system's ``initial_prior``). Use it through :func:`ceemx.fit`
    (``solver=ceemx.ParticleEM(...)``) or :func:`ceemx.particle_em`.

    Attributes:
        n_particles: N, particles per trajectory (paper: 100).
        n_smoothed: S, FFBSi trajectories per data trajectory and epoch (paper: 10).
        learner: the M-step optimiser (any ceemx learner; default Levenberg–Marquardt).
        burn_in: epochs with γ = 1.
        alpha: decay exponent of γ after the burn-in, 0.5 < α ≤ 1.
        memory: M, epochs of draws kept for Q̂ (see the module docs).
        proposal: ``"auto"``, ``"adapted"`` or ``"bootstrap"`` (see :func:`ceemx.particle_filter`).
        ess_threshold: resample when ESS < threshold·N.
        initial: the distribution of x₁ (default: the system's ``initial_prior``).
        rho_theta: ρ_θ ≥ 0, proximal weight of the M-step.
        rtol, atol: optional stopping rule on the change of θ (default 0: run ``max_epochs``).
    """

    n_particles: int = eqx.field(default=100, static=True)
    n_smoothed: int = eqx.field(default=10, static=True)
    learner: _learners.AbstractLearner = eqx.field(default_factory=_learners.LMLearner)
    burn_in: int = eqx.field(default=5, static=True)
    alpha: float = 0.7
    memory: int = eqx.field(default=10, static=True)
    proposal: str = eqx.field(default="auto", static=True)
    ess_threshold: float = 0.5
    initial: GaussianPrior | None = None
    rho_theta: float = 0.0
    rtol: float = 0.0
    atol: float = 0.0

    history_keys = {
        "pf_log_likelihood": "Σ_b log p̂(y_b | θₖ), the particle filter's estimate at this "
        "epoch's starting θ (failed trajectories left out)",
        "pf_log_likelihood_per_trajectory": "log p̂(y_b | θₖ) per trajectory",
        "saem_objective": "Q̂ₖ(θₖ₊₁): the SAEM objective (mean log p(x, y | θ) over the stored "
        "draws, SAEM-weighted) at the new θ",
        "step_size": "γₖ",
        "saem_mass": "SAEM weight mass kept in memory before renormalising (1: Q̂ exact)",
        "e_step_time": "seconds in the particle filter and FFBSi",
        "m_step_time": "seconds in the M-step (learner)",
        "min_ess": "smallest effective sample size of any step of any trajectory",
        "resampling_rate": "fraction of filter steps that resampled",
        "learner_steps": "iterations of the learner",
        "learner_status": "the learner's RESULTS code",
    }

    def __check_init__(self):
        for name in ("n_particles", "n_smoothed", "memory"):
            check_int(name, getattr(self, name), 1)
        check_int("burn_in", self.burn_in, 0)
        alpha = check_real("alpha", self.alpha)
        if alpha is not None and not (np.all(alpha > 0.5) and np.all(alpha <= 1.0)):
            raise ValueError(f"`alpha` must be in (0.5, 1]; got {self.alpha}.")
        check_proposal(self.proposal)
        check_threshold(self.ess_threshold)
        if not isinstance(self.learner, _learners.AbstractLearner):
            raise TypeError(f"`learner` must be a ceemx learner; got {self.learner!r}.")
        if self.initial is not None and not isinstance(self.initial, GaussianPrior):
            raise TypeError(
                "`initial` must be None or a ceemx.GaussianPrior; got "
                f"{type(self.initial).__name__}."
            )
        for name in ("rho_theta", "rtol", "atol"):
            check_nonnegative(name, getattr(self, name))

    def check_problem(self, problem: FitProblem, theta: Theta) -> None:
        """The base class's refusals, and a proposal or x₁ prior it cannot use, before any compute.

        (The start's health test would otherwise compile its programs for a fit refused after it.)
        """
        super().check_problem(problem, theta)
        resolve_proposal(problem.build(theta), self.proposal, self._prior(problem, theta))

    def _prior(self, problem: FitProblem, theta: Theta) -> GaussianPrior:
        """``initial``, else the system's ``initial_prior`` (validated; raises if neither)."""
        return initial_prior(problem.build(theta), self.initial)

    def initial_states(self, system, data) -> States:
        """Only the states reported before epoch 1: least squares through the observation map."""
        from ceemx.identification.initialize import from_observations

        return from_observations(system, data)

    def init(
        self, problem: FitProblem, theta: Theta, states: States, key: PRNGKeyArray
    ) -> FitState:
        """θ and x as given, an empty sample memory, the PRNG key and the learner's state."""
        prior = self._prior(problem, theta)
        resolve_proposal(problem.build(theta), self.proposal, prior)  # raises early
        B, T, n = states.shape
        M, S = self.memory, self.n_smoothed
        k_learner, k_run = jax.random.split(key)
        saem = SAEMState(
            key=k_run,
            epoch=jnp.zeros((), jnp.int32),
            samples=jnp.zeros((M, B, S, T, n), states.dtype),
            saem_weights=jnp.zeros((M,), states.dtype),
            valid=jnp.zeros((M, B), bool),
            learner_state=self.learner.init(theta, k_learner),
        )
        return starting_state(problem, theta, states, saem)

    def step(self, problem: FitProblem, state: FitState) -> tuple[FitState, dict[str, Any]]:
        """One E-step (filter + FFBSi) and one SAEM M-step."""
        saem: SAEMState = state.solver_state
        system = problem.build(state.theta)
        prior = self._prior(problem, state.theta)
        proposal = resolve_proposal(system, self.proposal, prior)
        k_pf, k_bs, k_next = jax.random.split(saem.key, 3)

        t0 = time.perf_counter()
        threshold = jnp.asarray(self.ess_threshold, state.states.dtype)
        pf = filter_batch(system, problem.data, prior, k_pf, threshold, self.n_particles, proposal)
        draws = ffbsi_batch(system, problem.data, pf, k_bs, self.n_smoothed)
        draws.block_until_ready()
        t_e = time.perf_counter() - t0

        ok_now = np.asarray(pf.status == RESULTS.successful) & np.asarray(
            jnp.all(jnp.isfinite(draws), axis=(1, 2, 3))
        )
        if not ok_now.all():
            warn(
                f"particle filtering failed (non-finite likelihood estimate) on trajectories "
                f"{np.flatnonzero(~ok_now).tolist()} at epoch {int(saem.epoch) + 1}; their draws "
                "are left out of the M-step."
            )
        ok = as_jax(ok_now)

        t0 = time.perf_counter()
        theta, saem_new, info, q_value, gamma, mass = _saem_update(
            self, problem, state.theta, saem, draws, ok, k_next
        )
        theta.block_until_ready()
        t_m = time.perf_counter() - t0

        # The states reported: the mean of this epoch's draws (failed trajectories keep theirs).
        mean = jnp.mean(draws, axis=1)
        states = jnp.where(ok[:, None, None], mean, state.states)
        status = select(ok, RESULTS.successful, RESULTS.particle_failure)
        new = FitState(
            theta=theta,
            states=states,
            J=trajectory_log_likelihood(problem, theta, states),
            weights=jnp.asarray(ok, state.states.dtype),
            status=status,
            solver_state=saem_new,
        )
        ll = np.asarray(pf.log_likelihood)
        record = {
            "pf_log_likelihood": float(np.sum(np.where(ok_now, ll, 0.0))),
            "pf_log_likelihood_per_trajectory": ll.tolist(),
            "saem_objective": float(q_value),
            "step_size": float(gamma),
            "saem_mass": float(mass),
            "e_step_time": t_e,
            "m_step_time": t_m,
            "min_ess": float(np.min(to_host(pf.ess))),
            "resampling_rate": float(np.mean(to_host(pf.resampled)[:, 1:])),
            "learner_steps": int(info.steps),
            "learner_status": int(codes(info.status)),
        }
        return new, record

    def terminate(
        self, problem: FitProblem, before: FitState, after: FitState, record: dict[str, Any]
    ) -> tuple[bool, bool]:
        """Stop when every trajectory failed; converge on the θ-change rule if asked."""
        if not np.any(np.asarray(after.weights) > 0):
            return True, False
        rtol, atol = float(self.rtol), float(self.atol)
        if rtol == 0.0 and atol == 0.0:
            return False, False
        epoch = int(after.solver_state.epoch)
        if epoch <= self.burn_in:
            return False, False
        th0, th1 = np.asarray(before.theta), np.asarray(after.theta)
        converged = bool(np.linalg.norm(th1 - th0) <= rtol * np.linalg.norm(th1) + atol)
        return converged, converged


def saem_problem(
    problem: FitProblem,
    theta: Theta,
    samples: Float[Array, "M B S T n"],
    weights: Float[Array, " M"],
    valid: Bool[Array, "M B"],
    rho_theta: Scalar,
) -> LearningProblem:
    """Q̂ as a weighted learning problem over the stored draws (each paired with its data)."""
    M, B, S, T, n = samples.shape
    data = problem.data

    def tile(a):
        a = jnp.broadcast_to(a[None, :, None], (M, B, S) + a.shape[1:])
        return a.reshape((M * B * S,) + a.shape[3:])

    tiled = eqx.tree_at(
        lambda d: (d.y, d.u, d.mask), data, (tile(data.y), tile(data.u), tile(data.mask))
    )
    per = jnp.where(valid, weights[:, None], 0.0)  # (M, B)
    per = jnp.broadcast_to(per[:, :, None], (M, B, S)) / S
    total = jnp.sum(weights)
    w = (per / jnp.where(total > 0, total, 1.0)).reshape(-1)
    tiled_problem = eqx.tree_at(lambda p: p.data, problem, tiled)
    return LearningProblem(
        problem=tiled_problem,
        states=samples.reshape((M * B * S, T, n)),
        weights=w,
        theta_ref=theta,
        rho_theta=rho_theta,
    )


@jit
def _saem_update(
    solver: ParticleEM,
    problem: FitProblem,
    theta: Theta,
    saem: SAEMState,
    draws: Float[Array, "B S T n"],
    ok: Bool[Array, " B"],
    key: PRNGKeyArray,
):
    """Store the draws, update the SAEM weights, run the learner on Q̂ (compiled once)."""
    epoch = saem.epoch + 1
    gamma = saem_step_size(epoch, solver.burn_in, solver.alpha).astype(theta.dtype)
    slot = (epoch - 1) % solver.memory
    weights = (1.0 - gamma) * saem.saem_weights
    weights = weights.at[slot].set(gamma)
    samples = saem.samples.at[slot].set(jnp.where(ok[:, None, None, None], draws, 0.0))
    valid = saem.valid.at[slot].set(ok)
    mass = jnp.sum(weights)
    rho = jnp.asarray(solver.rho_theta, theta.dtype)
    lp = saem_problem(problem, theta, samples, weights, valid, rho)
    theta_new, learner_state, info = solver.learner.run(lp, theta, saem.learner_state)
    # Q̂ at the new θ: the learner's final objective less the trust region and the prior (every
    # learner reports value_after = the objective at the θ it returns).
    q_value = -(info.value_after - lp.regulariser(theta_new))
    new = SAEMState(key, epoch, samples, weights, valid, learner_state)
    return theta_new, new, info, q_value, gamma, mass
