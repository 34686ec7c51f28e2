"""``learn``: one θ-step on fixed states (paper Eq. 11)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PRNGKeyArray

from ceemx.data.checks import prepare
from ceemx.data.trajectories import Trajectories
from ceemx.identification.learning.learners import AbstractLearner, LearnInfo, LMLearner
from ceemx.identification.learning.learning_problem import AbstractLearningProblem, make_problem
from ceemx.infra.compilation import jit
from ceemx.infra.options import check_key, check_nonnegative
from ceemx.infra.policy import entry_point
from ceemx.lib.tree import trace_numbers
from ceemx.lib.typing import PerTrajectory, Theta
from ceemx.models.system import AbstractSystem

__all__ = ["learn", "run_learner"]


@jit
def run_learner(
    learner: AbstractLearner, problem: AbstractLearningProblem, theta: Theta, state: Any
) -> tuple[Theta, Any, LearnInfo]:
    """Run a learner, compiled once per learner type, problem shape and dtype."""
    return learner.run(problem, theta, state)


@entry_point  # BLAS threads and results as the policy says (ceemx.infra.policy)
def learn(
    system: AbstractSystem,
    states: Float[ArrayLike, "B T n"],
    data: Trajectories,
    learner: AbstractLearner | None = None,
    *,
    trainable=None,
    rho_theta: float = 0.0,
    log_prior: Callable[[AbstractSystem], Any] | None = None,
    weights: ArrayLike | Sequence[float] | None = None,
    learner_state: Any = None,
    key: PRNGKeyArray | None = None,
) -> tuple[AbstractSystem, Any, LearnInfo]:
    """One learning step: θ ← argmin Σ_b −J_b(x_b, θ) + ρ_θ‖θ − θᵏ‖² − log p(θ).

    Args:
        system: the model at θᵏ.
        states: (B, T, n) fixed state trajectories (e.g. a smoother's output).
        data: the observations.
        learner: the optimiser (default :class:`LMLearner`).
        trainable: which leaves learn (see :func:`ceemx.identification.problem.trainable_mask`).
        rho_theta: trust-region weight ρ_θ ≥ 0.
        log_prior: optional ``system -> log p(θ)``.
        weights: (B,) 0/1 weights; 0 excludes a trajectory (e.g. one whose smoothing failed).
        learner_state: state from a previous call (``None``: ``learner.init``).
        key: PRNG key for stochastic learners.

    Returns:
        (new system, learner state, :class:`LearnInfo`), in the system's dtype: ``states``, the
        data and the system's noise are first cast to the dtype of its parameters
        (:func:`ceemx.data.checks.promote_inputs`).

    Raises:
        ValueError, TypeError: naming the argument, as :func:`ceemx.smooth` does for ``states``
            (which must be (B, T, n) and finite), for a ``rho_theta`` that is not finite and
            >= 0, and for a ``trainable`` that selects no parameter. Warns in float32.
    """
    learner = LMLearner() if learner is None else learner
    if not isinstance(learner, AbstractLearner):
        raise TypeError(f"`learner` must be a ceemx learner; got {learner!r}.")
    check_nonnegative("rho_theta", rho_theta)
    if key is not None:
        check_key(key)
    inputs = prepare(system, data, states, name="states", unobserved_warning=False)
    system, data, states = inputs.system, inputs.data, jnp.asarray(inputs.states)
    weights = _check_weights(weights, data.batch_size)
    learner = trace_numbers(learner, states.dtype)
    problem, theta = make_problem(
        system,
        states,
        data,
        trainable=trainable,
        rho_theta=rho_theta,
        log_prior=log_prior,
        weights=weights,
    )
    if learner_state is None:
        learner_state = learner.init(theta, jax.random.PRNGKey(0) if key is None else key)
    theta_new, learner_state, info = run_learner(learner, problem, theta, learner_state)
    return problem.build(theta_new), learner_state, info


def _check_weights(weights, B: int) -> PerTrajectory | None:
    """``weights`` as (B,) finite non-negative floats (``None`` passes), or raise naming them."""
    if weights is None:
        return None
    try:
        w = np.asarray(weights, np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"`weights` must be (B,) = ({B},) numbers; got {weights!r:.80}.") from None
    if w.shape != (B,) or not np.all(np.isfinite(w) & (w >= 0)):
        raise ValueError(
            f"`weights` must be (B,) = ({B},) finite numbers >= 0; got shape {w.shape}: {w!r:.80}."
        )
    return jnp.asarray(weights)
