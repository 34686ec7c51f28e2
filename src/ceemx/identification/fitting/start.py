"""The start of a fit: its problem, start states and first state, from prepared inputs.

:func:`start_fit` builds the :class:`~ceemx.identification.problem.FitProblem` once (the
trajectories the health test excludes become a sub-problem of it), has the solver refuse what it
cannot fit, computes the start states (while a background thread compiles the solver's epoch
programs), screens the trajectories (:mod:`~ceemx.identification.fitting.health`) and returns the
solver's first state — or the one a checkpoint of the same fit resumes.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ceemx.data.arrays import indexed
from ceemx.data.checks import Prepared, check_states, prepare
from ceemx.data.sharding import shard_batch
from ceemx.data.trajectories import Trajectories
from ceemx.identification.analysis.summary import describe_noise
from ceemx.identification.fitting.choice import choose, problem_facts
from ceemx.identification.fitting.fit_options import FitOptions, check_against_start
from ceemx.identification.fitting.health import (
    Health,
    check_start,
    failed_start,
    no_finite_start,
    trajectory_health,
)
from ceemx.identification.problem import FitProblem, Trainable
from ceemx.identification.solvers.base import AbstractFitSolver, FitState, total_J
from ceemx.infra import checkpoint as ckpt
from ceemx.infra.compilation import BackgroundCompile, compile_in_background
from ceemx.infra.distributed import is_main_process, to_host
from ceemx.infra.policy import compiles_ahead
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS
from ceemx.lib.tree import as_jax, trace_numbers
from ceemx.lib.typing import States, Theta
from ceemx.models.system import AbstractSystem

__all__ = [
    "FitStart",
    "all_failed",
    "gathered",
    "precompile_fit",
    "refuse_failed_start",
    "require_observations",
    "screen_outliers",
    "start_fit",
]


@dataclasses.dataclass
class FitStart:
    """Where the epochs start (:func:`start_fit`).

    Attributes:
        solver: the solver, its numbers traced (:func:`ceemx.lib.trace_numbers`).
        problem: the problem over the trajectories taking part.
        theta: θ at the start (unconstrained).
        state: the solver's first state, or the resumed one.
        history: the resumed epochs' records (``[]`` for a new fit).
        initial_J: J at the start.
        all_states: (B, T, n) start states of every trajectory.
        excluded: (B,) the trajectories the health test excluded.
        health: the health test's record (``None`` with ``outliers="keep"``).
        fingerprint: what identifies the fit in its checkpoint (``None`` without one).
        compiling: the thread compiling the solver's epoch programs (``None``: none), to join
            before the first epoch.
    """

    solver: AbstractFitSolver
    problem: FitProblem
    theta: Theta
    state: FitState
    history: list[dict]
    initial_J: float
    all_states: States
    excluded: np.ndarray
    health: Health | None
    fingerprint: dict | None
    compiling: BackgroundCompile | None


def start_fit(
    system: AbstractSystem, inputs: Prepared, options: FitOptions, hold: contextlib.ExitStack
) -> FitStart:
    """The start of a fit of ``system`` as given, from its prepared inputs.

    The checkpoint folder is checked and its lock entered into ``hold`` (held until the fit
    ends) before any compute.
    """
    solver = options.solver
    if options.checkpoint is not None:
        ckpt.check_folder(options.checkpoint, options.checkpoint_mismatch)
        if not options.spread or is_main_process():  # process 0 alone writes a spread fit's
            hold.enter_context(ckpt.lock(options.checkpoint))
    # the problem is built from the system as given (its weakly typed leaves cast to its dtype)
    problem, theta = FitProblem.create(
        system,
        inputs.data,
        trainable=options.trainable,
        log_prior=options.log_prior,
        overrides=options.overrides,
    )
    solver.check_problem(problem, theta)  # what it refuses, before any compute
    compiling = _precompile(solver, problem, theta, inputs, options)
    states, problem, solver = _start_states(solver, problem, inputs, options)
    excluded, health = screen_outliers(problem, theta, states, options.outliers)
    # refuses absurd or non-finite starts, then tolerances and trust regions no fit can fail
    tested = check_start(problem, theta, states, health, excluded)
    take = ~excluded & np.isfinite(tested.mean_square)
    check_against_start(
        options.solver, tested.misfit(take), float(np.sum(tested.count[take])), theta, states
    )
    all_states = states
    if excluded.any():
        keep = np.flatnonzero(~excluded)
        states, problem = indexed(states, keep), problem.subset(keep)
    key = jax.random.PRNGKey(0) if options.key is None else options.key
    state = solver.init(problem, theta, states, key)
    if all_failed(state):
        refuse_failed_start(problem, theta, states, solver, at_init=True)
    initial_J = total_J(state)
    state, history, fingerprint = _resume(solver, problem, theta, state, options)
    return FitStart(
        solver,
        problem,
        theta,
        state,
        history,
        initial_J,
        all_states,
        excluded,
        health,
        fingerprint,
        compiling,
    )


def require_observations(data: Trajectories) -> None:
    """Refuse data with no observed entry (every y masked): nothing to fit θ or states to.

    Raises:
        ValueError: naming ``data``, before any compute.
    """
    mask = np.asarray(data.mask)
    if not mask.any():
        B, T, m = data.y.shape
        raise ValueError(
            f"`data` holds no observation: every entry of y ({B} trajectories × {T} steps × {m} "
            "outputs) is masked, so J has no data term and any fit would 'converge' at its "
            "start. Pass data with at least one observed entry (mask True)."
        )


def all_failed(state: FitState) -> bool:
    """Whether no trajectory of ``state`` can go on: none takes part, or every one is non-finite."""
    ok = to_host(state.weights) > 0
    if not ok.any():
        return True
    nonfinite = np.asarray(to_host(state.status == RESULTS.nonfinite)).reshape(-1)
    return bool(np.all(nonfinite[ok]))


def refuse_failed_start(
    problem: FitProblem,
    theta: Theta,
    states: States,
    solver: AbstractFitSolver,
    *,
    at_init: bool,
) -> None:
    """Raise the reason a fit failed on every trajectory at its start, when there is one.

    Called when the solver's ``init`` (``at_init``) or its first epoch left no trajectory to fit
    from a start whose J is finite (:func:`check_start`): the gradient of J at the start,
    where not finite, named by :func:`~ceemx.identification.fitting.health.failed_start`. A
    failed ``init`` with a finite gradient (Laplace EM's E-step: a posterior covariance not
    finite) is refused too, naming the noise models; a first epoch that failed from a start with
    a finite gradient is not (its step led there: the fit ends with that status).

    Raises:
        ValueError: as above.
    """
    reason = failed_start(problem, theta, states)
    if reason is None and at_init:
        noise = _noise_of(problem.build(theta))
        reason = (
            f"the fit cannot start: {type(solver).__name__}'s first evaluation failed on every "
            "trajectory although J and its gradient are finite there (for LaplaceEM: the E-step's "
            "posterior covariance is not finite, as when a noise scale is near zero). The noise "
            f"models: {noise}. Start from noise scales of the size of the residuals "
            "(ceemx.estimate_noise) or other initial parameters."
        )
    if reason is not None:
        raise ValueError(reason)


def _precompile(
    solver: AbstractFitSolver, problem: FitProblem, theta: Theta, inputs: Prepared, options
) -> BackgroundCompile | None:
    """The thread compiling the solver's epoch programs while the start states are computed.

    ``None`` for a solver without :meth:`AbstractFitSolver.precompile`, with ``devices``, or
    where the policy compiles in the foreground (:func:`ceemx.infra.policy.compiles_ahead`).
    """
    if (
        options.mesh is not None
        or type(solver).precompile is AbstractFitSolver.precompile
        or not compiles_ahead()
    ):
        return None
    traced = trace_numbers(solver, inputs.dtype)
    return compile_in_background(traced.precompile(problem, theta, _placeholder(inputs)))


def _start_states(
    solver: AbstractFitSolver, problem: FitProblem, inputs: Prepared, options
) -> tuple[States, FitProblem, AbstractFitSolver]:
    """(start states, the problem over the placed data, the solver with its numbers traced).

    Without given states, the solver's ``initial_states`` (checked as given ones are).
    """
    states = inputs.states
    if states is None:
        states = solver.initial_states(inputs.system, inputs.data)
        try:
            check_states(inputs.system, inputs.data, states)
        except ValueError as err:  # x_init was not given: say where the states came from
            raise ValueError(
                f"the warm start (x_init=None: {type(solver).__name__}.initial_states) gave "
                f"states no fit can start from: {str(err).replace('`x_init` has', 'it has')} The "
                "model is not finite where least squares through the observation map put the "
                "states (e.g. a logarithm of a negative state), or the initial parameters or "
                f"noise are far off ({_noise_of(inputs.system)}): pass x_init, or other initial "
                "parameters or noise."
            ) from None
    states = as_jax(states)
    if options.mesh is not None:
        data, states = shard_batch(inputs.data, states, options.mesh)
        problem = problem.with_data(data)
    return states, problem, trace_numbers(solver, states.dtype)


def _noise_of(system: AbstractSystem) -> str:
    """The system's noise models in a few words (for messages)."""
    return "; ".join(
        f"{field}: {describe_noise(getattr(system, field))}"
        for field in ("process_noise", "obs_noise")
    )


def _placeholder(inputs: Prepared) -> States:
    """The start states, or zeros of their shape and dtype (the programs depend on those alone)."""
    if inputs.states is not None:
        return as_jax(inputs.states)
    B, T, _ = inputs.data.y.shape
    return jnp.zeros((B, T, inputs.system.state_dim), inputs.dtype)


def screen_outliers(problem: FitProblem, theta: Theta, states: States, outliers: str):
    """The start-of-fit health test: (trajectories to exclude, the health record or ``None``)."""
    excluded = np.zeros((problem.data.batch_size,), bool)
    if outliers == "keep":
        return excluded, None
    health = trajectory_health(problem, theta, states)
    if not np.any(np.isfinite(health.mean_square)):
        raise ValueError(no_finite_start(problem, theta, problem.data.batch_size))
    bad = health.flagged & np.isfinite(health.mean_square)
    if bad.any():
        idx = np.flatnonzero(bad)
        action = "excluded from the fit" if outliers == "exclude" else "kept (outliers='warn')"
        warn(
            f"trajectories {health.describe(idx)} have residuals far outside the noise model "
            f"(mean squared whitened residual; median {health.median:.3g}): {action}. "
            "Pass outliers='keep' to skip this test (ceemx.identification.fitting.health)."
        )
        if outliers == "exclude":
            excluded = bad
    return excluded, health


def _resume(solver, problem: FitProblem, theta: Theta, state: FitState, options: FitOptions):
    """(state, history, fingerprint): a checkpoint of the same fit resumed, else the start."""
    if options.checkpoint is None:
        return state, [], None
    template, local = dataclasses.replace(state, cache=None), problem
    if options.spread:  # fingerprint and load on gathered arrays (a resumed state is local)
        template, local = gathered(template), problem.with_data(gathered(problem.data))
    fingerprint = ckpt.fingerprint(template, local, theta, solver)
    loaded = ckpt.load(
        options.checkpoint, template, fingerprint, mismatch=options.checkpoint_mismatch
    )
    if loaded is None:
        return state, [], fingerprint
    state, history = loaded
    return state, history, fingerprint


def gathered(tree):
    """``tree`` with every array gathered onto this process (after a multi-process fit)."""
    return jax.tree.map(lambda a: as_jax(to_host(a)) if eqx.is_array(a) else a, tree)


def precompile_fit(
    system: AbstractSystem,
    data: Trajectories,
    x_init: Any = None,
    *,
    solver: AbstractFitSolver | None = None,
    trainable: Trainable = None,
    log_prior=None,
) -> BackgroundCompile:
    """Start compiling the epoch programs of the same :func:`ceemx.fit` call, in the background.

    :func:`ceemx.fit` does this itself while it computes the start states; call this when the
    start states or the data come from your own work first (a warm start, loading, simulation),
    so the compiler runs meanwhile on another core, then ``join()`` the thread before calling
    :func:`ceemx.fit` with the same ``system``, ``data`` shapes, ``solver``, ``trainable`` and
    ``log_prior``. ``x_init`` may be ``None`` (the programs depend only on the states' shape and
    dtype). Nothing is computed: only :meth:`AbstractFitSolver.precompile` (no-op for solvers
    without one); ``solver=None``: the first stage of the default path
    (:func:`~ceemx.identification.fitting.choice.choose`). Arguments are validated as by
    :func:`ceemx.fit`.

    Returns:
        The started :class:`~ceemx.infra.compilation.BackgroundCompile`; its ``join()`` runs
        the jobs the worker has not started yet in the calling thread, then waits for the worker.
    """
    if solver is not None and not isinstance(solver, AbstractFitSolver):
        raise TypeError(f"`solver` must be a fit solver; got {solver!r}.")
    inputs = prepare(system, data, x_init)
    problem, theta = FitProblem.create(
        system, inputs.data, trainable=trainable, log_prior=log_prior
    )
    if solver is None:  # the default path's first stage on all the data
        solver = choose(**problem_facts(problem, theta, system)).stages[0].solver
    traced = trace_numbers(solver, inputs.dtype)
    return compile_in_background(traced.precompile(problem, theta, _placeholder(inputs)))
