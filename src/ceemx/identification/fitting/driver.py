"""``fit``: the one entry point that identifies θ and the states, with any fit solver.

It checks the options, prepares the inputs once (:func:`ceemx.data.checks.prepare`) and runs one
fit at the system's noise (:func:`~ceemx.identification.fitting.run.run_fit`: start, epochs,
finish) or rounds of them that learn the noise
(:func:`~ceemx.identification.fitting.noise_rounds.learn_noise`); without a solver, the stages
the library chooses from the problem (:mod:`~ceemx.identification.fitting.default_path`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

from jax.sharding import Mesh
from jaxtyping import ArrayLike, PRNGKeyArray

from ceemx.data.checks import prepare
from ceemx.data.trajectories import Trajectories
from ceemx.identification.fitting.choice import choose, problem_facts
from ceemx.identification.fitting.default_path import check_checkpoint, fit_default, user_choice
from ceemx.identification.fitting.fit_options import fit_options
from ceemx.identification.fitting.noise_rounds import learn_noise
from ceemx.identification.fitting.result import EpochInfo, FitResult
from ceemx.identification.fitting.run import run_fit
from ceemx.identification.fitting.start import require_observations
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.base import AbstractFitSolver
from ceemx.infra.policy import entry_point
from ceemx.lib.typing import no_type_check
from ceemx.models.system import AbstractSystem

__all__ = ["fit"]

_INPUTS = ("system", "data", "x_init")


@entry_point  # BLAS threads and results as the policy says (ceemx.infra.policy)
@no_type_check  # validates its arguments: the options, then ceemx.data.checks.prepare
def fit(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike | None = None,
    *,
    solver: AbstractFitSolver | None = None,
    trainable=None,
    log_prior: Callable[[AbstractSystem], Any] | None = None,
    max_epochs: int = 100,
    callbacks: Sequence[Callable[[EpochInfo], Any]] = (),
    progress: bool | None = None,
    checkpoint: str | None = None,
    checkpoint_mismatch: Literal["raise", "restart"] = "raise",
    key: PRNGKeyArray | None = None,
    outliers: str = "exclude",
    devices: Literal["all"] | Mesh | None = None,
    diagnose: bool = True,
    noise: Literal["fixed", "learn"] | None = None,
) -> FitResult:
    """Identify θ and the state trajectories by maximising the CE-EM objective J(x, θ) (Eq. 9).

    Args:
        system: the model at its initial θ.
        data: B observed trajectories.
        x_init: (B, T, n) initial states (``None``: the solver's ``initial_states``, for the CE
            methods :func:`ceemx.warm_start`).
        solver: the method — :class:`ceemx.Alternating` (the paper's Algorithm 1),
            :class:`ceemx.JointLM`, :class:`ceemx.LaplaceEM` (learns noise covariances) or
            :class:`ceemx.ParticleEM`; its tolerances decide convergence. ``None`` (default):
            the library chooses from the problem (below, "The default path"), and
            :attr:`FitResult.choice` and the summary say what and why.
        trainable: which leaves learn (``None``: all model arrays except noise and prior; a
            callable ``where(system)`` or a boolean filter pytree). Noise models only with a
            solver that learns noise (:class:`ceemx.LaplaceEM`).
        log_prior: optional ``system -> log p(θ)``.
        max_epochs: bound on epochs (iterations of the solver).
        callbacks: called with an :class:`EpochInfo` after every epoch; a returned dict is merged
            into that epoch's history record; returning ``False`` stops the fit.
        progress: show a progress bar (``None``: only when stderr is a terminal).
        checkpoint: folder the state is written to atomically after every epoch, and resumed
            from when it holds a checkpoint of the same fit (``docs/guarantees.md``); held by
            this fit alone (a lock on its ``.lock`` file) until it returns.
        checkpoint_mismatch: for a checkpoint of another fit, corrupt or not finite:
            ``"raise"`` a :class:`ceemx.infra.checkpoint.CheckpointError` naming what differs, or
            ``"restart"`` (warn, start afresh, overwrite it).
        key: PRNG key for stochastic solvers and learners (default ``PRNGKey(0)``).
        outliers: the start-of-fit health test (:mod:`ceemx.identification.fitting.health`):
            ``"exclude"`` (default) fits without the trajectories whose residuals are far
            outside the noise model (named in a warning and :attr:`FitResult.excluded`; status
            ``outlier``), ``"warn"`` only names them, ``"keep"`` skips the test.
        devices: data parallelism over the trajectories (:mod:`ceemx.data.sharding`): ``None``
            (default), ``"all"`` visible devices, or a 1-D :class:`jax.sharding.Mesh`; results
            agree with ``None`` to rounding (several processes: see ``docs/guarantees.md``).
        diagnose: the end-of-fit noise check (:attr:`FitResult.noise_check`; warns when the
            residuals and the assumed noise disagree by more than 2× in standard deviation).
        noise: ``"fixed"`` fits at the system's noise models; ``"learn"`` learns one
            factor on each from the data, CE fits alternated with the maximiser of the Laplace
            log-evidence until they settle (``FitResult.noise_rounds``; ``max_epochs`` bounds
            each round; not with ``checkpoint``; for :class:`ceemx.Alternating` and
            :class:`ceemx.JointLM`); the observation noise has floors from the data and
            never collapses (``docs/guarantees.md``, "Learned noise"). ``None`` (default):
            ``"fixed"`` with a named solver; without one, learned wherever the default path can
            learn it.

    The default path (``solver=None``; :func:`~ceemx.identification.fitting.choice.choose`,
    measured in ``docs/decisions.md``): with at most 200 parameters in θ and Gaussian noise
    models, :class:`ceemx.JointLM` with the noise learned (``noise="fixed"``: as given), then
    :class:`ceemx.LaplaceEM` in θ alone at that noise from the joint fit's θ and states — the
    estimate at the maximum of the Laplace evidence, free of the certainty-equivalent bias, and
    intervals of the evidence; on long data (B·T ≥ 40 000) the noise is learned on the first
    2 500 steps and the finish takes quasi-Newton steps; the finish is skipped (and the summary
    says why) where the joint fit's covariance is not positive definite. More than 200 parameters:
    :class:`ceemx.Alternating` at the given noise. ``trainable`` selecting noise models:
    :class:`ceemx.LaplaceEM`. Data over several processes, or noise models that are not
    Gaussian: :class:`ceemx.JointLM` at the given noise. A multi-stage path returns one result
    (the last stage's estimate; ``history`` of every stage; converged when every stage
    converged); with ``checkpoint`` it needs ``noise="fixed"`` (each stage checkpoints in a
    folder of its own) — the noise rounds do not checkpoint.

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError, TypeError: on invalid inputs or options, before any compute;
            :class:`ceemx.infra.checkpoint.CheckpointError` for an unwritable or busy
            ``checkpoint`` folder, or a checkpoint that cannot be resumed.

    Example:
        >>> result = ceemx.fit(guess, data, solver=ceemx.JointLM(), trainable=lambda s: s.rho)
        ... # doctest: +SKIP
    """
    # every option, checked before any compute (the inputs are prepared next)
    options = fit_options(**{k: v for k, v in locals().items() if k not in _INPUTS})
    t0 = time.perf_counter()
    inputs = prepare(system, data, x_init, identify=True)
    require_observations(inputs.data)  # every solver, every noise mode: before any compute
    if solver is None:
        problem, theta = FitProblem.create(
            system, inputs.data, trainable=trainable, log_prior=log_prior
        )
        facts = problem_facts(problem, theta, system, options.spread, options.mesh is not None)
        choice = choose(noise=noise, **facts)
        check_checkpoint(choice, options)
        return fit_default(system, inputs, options, choice)
    result = (
        learn_noise(system, inputs, options)
        if noise == "learn"
        else run_fit(system, inputs, options)
    )
    choice = user_choice(result, solver, noise, time.perf_counter() - t0)
    return dataclasses.replace(result, choice=choice)
