"""``fit``: the one host-side driver that runs any fit solver.

The driver owns what every method needs — input validation, the initial states, dtype handling,
the epoch loop with its history, callbacks, progress bar, timing and atomic checkpoints with
resume — and delegates the mathematics to the solver object (:mod:`ceemx.solvers`).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, PRNGKeyArray

from . import checkpoint as ckpt
from .data import Trajectories
from .lib.results import RESULTS, messages
from .lib.tree import trace_numbers
from .models.system import AbstractSystem
from .problem import FitProblem
from .smoothing import check_inputs
from .solvers.alternating import Alternating
from .solvers.base import AbstractFitSolver, FitState, total_J
from .solvers.particle_em import ParticleEM
from .typing import States, no_type_check

__all__ = ["EpochInfo", "FitResult", "fit", "particle_em"]


@dataclasses.dataclass
class EpochInfo:
    """What a callback receives after each epoch.

    Attributes:
        epoch: 1-based epoch number.
        system: the system after this epoch.
        states: (B, T, n) states after this epoch.
        record: this epoch's history record (a dict; callbacks may add entries to it).
    """

    epoch: int
    system: AbstractSystem
    states: States
    record: dict


class FitResult(eqx.Module):
    """The outcome of :func:`fit`, the same for every solver.

    Attributes:
        system: the learned system.
        states: (B, T, n) state trajectories at the end.
        status: (B,) per-trajectory :class:`ceemx.RESULTS`.
        history: one dict per epoch. Keys every solver has: ``epoch``, ``time`` (seconds of the
            epoch), ``J`` (total log-likelihood, Eq. 9, over the trajectories taking part),
            ``J_before``, ``J_per_trajectory``, ``dtheta_norm``, ``dx_norm``,
            ``failed_trajectories``, ``converged``, ``stop``; plus the solver's own
            (``type(solver).history_keys``) and whatever callbacks returned (e.g. ``eps``).
        converged: whether the solver's stopping criterion was met (else ``max_epochs`` ran out,
            a callback stopped the fit, or every trajectory failed).
        solver: the solver that produced it.
        initial_J: J at the initial (x, θ).
    """

    system: AbstractSystem
    states: States
    status: RESULTS
    history: list = eqx.field(static=True)
    converged: bool = eqx.field(static=True)
    solver: AbstractFitSolver
    initial_J: float = eqx.field(static=True)

    @property
    def epochs(self) -> int:
        """Number of epochs run, including resumed ones."""
        return len(self.history)

    def history_array(self, name: str) -> np.ndarray:
        """One history entry across epochs as an array."""
        return np.asarray([h[name] for h in self.history])

    def messages(self) -> list[str]:
        """One status message per trajectory."""
        return messages(self.status)


class _Progress:
    def __init__(self, enabled: bool, total: int, initial: int, desc: str):
        self.bar = None
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=initial, desc=desc, unit="epoch", leave=True)

    def update(self, record):
        if self.bar is not None:
            self.bar.set_postfix(J=f"{record['J']:.6g}", t=f"{record['time']:.2f}s")
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _check_max_epochs(max_epochs) -> int:
    if isinstance(max_epochs, bool) or not isinstance(max_epochs, int | np.integer):
        raise TypeError(f"`max_epochs` must be an int; got {max_epochs!r}.")
    if max_epochs < 0:
        raise ValueError(f"`max_epochs` must be >= 0; got {max_epochs}.")
    return int(max_epochs)


@no_type_check  # validates its arguments: check_inputs, solver and max_epochs checks
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
    key: PRNGKeyArray | None = None,
) -> FitResult:
    """Identify θ and the state trajectories by maximising the CE-EM objective J(x, θ) (Eq. 9).

    Args:
        system: the model at its initial θ.
        data: B observed trajectories.
        x_init: (B, T, n) initial states (``None``: the solver's ``initial_states`` —
            :func:`ceemx.initialize.warm_start`, least squares through the observation map and a
            smoothing pass at the initial θ, for the CE methods).
        solver: the method — :class:`ceemx.Alternating` (the paper's Algorithm 1, default),
            :class:`ceemx.JointLM` (joint Levenberg–Marquardt on (x, θ)) or
            :class:`ceemx.ParticleEM` (particle filter + FFBSi + SAEM); its tolerances decide
            convergence.
        trainable: which leaves learn (``None``: all model arrays except noise and prior; a
            callable ``where(system)`` or a boolean filter pytree).
        log_prior: optional ``system -> log p(θ)``.
        max_epochs: bound on epochs (iterations of the solver).
        callbacks: called with an :class:`EpochInfo` after every epoch; a dict returned by a
            callback is merged into that epoch's history record; returning ``False`` stops.
        progress: show a progress bar (``None``: only when stderr is a terminal).
        checkpoint: folder; after every epoch the state is written there atomically, and an
            existing checkpoint there is resumed from.
        key: PRNG key for stochastic solvers and learners (default ``PRNGKey(0)``).

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError, TypeError: on invalid inputs (before any compute).

    Example:
        >>> result = ceemx.fit(guess, data, solver=ceemx.JointLM(), trainable=lambda s: s.rho)
        ... # doctest: +SKIP
    """
    solver = Alternating() if solver is None else solver
    if not isinstance(solver, AbstractFitSolver):
        raise TypeError(
            f"`solver` must be a fit solver such as ceemx.Alternating() or ceemx.JointLM(); "
            f"got {solver!r}."
        )
    max_epochs = _check_max_epochs(max_epochs)
    check_inputs(system, data)
    if x_init is None:
        x_init = solver.initial_states(system, data)
    check_inputs(system, data, x_init)
    states = jnp.asarray(x_init)
    solver = trace_numbers(solver, states.dtype)
    key = jax.random.PRNGKey(0) if key is None else key
    problem, theta = FitProblem.create(system, data, trainable=trainable, log_prior=log_prior)

    state = solver.init(problem, theta, states, key)
    initial_J = total_J(state)
    history: list[dict] = []
    if checkpoint is not None:
        loaded = ckpt.load(checkpoint, dataclasses.replace(state, cache=None))
        if loaded is not None:
            state, history = loaded

    show = sys.stderr.isatty() if progress is None else progress
    bar = _Progress(show, max_epochs, len(history), type(solver).__name__)
    converged = bool(history and history[-1].get("converged", False))
    stopped = bool(history and history[-1].get("stop", False))
    try:
        while len(history) < max_epochs and not (converged or stopped):
            epoch = len(history) + 1
            t0 = time.perf_counter()
            before = state
            state, own = solver.step(problem, state)
            elapsed = time.perf_counter() - t0
            record = _record(epoch, before, state, elapsed, own)
            stop, converged = solver.terminate(problem, before, state, record)
            system_now = problem.build(state.theta)
            info = EpochInfo(epoch, system_now, state.states, record)
            stopped = _run_callbacks(callbacks, info) or stop
            record["converged"] = converged
            record["stop"] = converged or stopped
            history.append(record)
            bar.update(record)
            if checkpoint is not None:
                ckpt.save(checkpoint, dataclasses.replace(state, cache=None), history)
    finally:
        bar.close()
    state = solver.postprocess(problem, state)
    return FitResult(
        problem.build(state.theta),
        state.states,
        state.status,
        history,
        converged,
        solver,
        initial_J,
    )


def _record(epoch: int, before: FitState, after: FitState, elapsed: float, own: dict) -> dict:
    """The driver's history keys (see :class:`FitResult`) and the solver's own."""
    ok = np.asarray(after.weights) > 0
    dx = np.where(ok[:, None, None], np.asarray(after.states) - np.asarray(before.states), 0.0)
    return {
        "epoch": epoch,
        "J_before": total_J(before),
        "J": total_J(after),
        "J_per_trajectory": np.asarray(after.J).tolist(),
        "dtheta_norm": float(np.linalg.norm(np.asarray(after.theta) - np.asarray(before.theta))),
        "dx_norm": float(np.linalg.norm(dx)),
        "failed_trajectories": np.flatnonzero(~ok).tolist(),
        "time": elapsed,
        **own,
    }


def _run_callbacks(callbacks, info: EpochInfo) -> bool:
    stop = False
    for cb in callbacks:
        out = cb(info)
        if isinstance(out, dict):
            info.record.update(out)
        elif out is False:
            stop = True
    return stop


@no_type_check  # validates its arguments through fit and ParticleEM
def particle_em(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike | None = None,
    *,
    n_particles: int = 100,
    n_smoothed: int = 10,
    learner=None,
    burn_in: int = 5,
    alpha: float = 0.7,
    memory: int = 10,
    initial=None,
    trainable=None,
    log_prior: Callable[[AbstractSystem], Any] | None = None,
    max_epochs: int = 50,
    callbacks: Sequence[Callable[[EpochInfo], Any]] = (),
    progress: bool | None = None,
    checkpoint: str | None = None,
    key: PRNGKeyArray | None = None,
    **options: Any,
) -> FitResult:
    """Particle EM (fully adapted particle filter, FFBSi, SAEM): ``fit`` with :class:`ParticleEM`.

    ``system``, ``data``, ``trainable``, ``log_prior``, ``max_epochs``, ``callbacks``,
    ``progress``, ``checkpoint`` and ``key`` are as for :func:`fit`; ``x_init`` only sets the
    states reported before epoch 1. ``n_particles``, ``n_smoothed``, ``learner`` (``None``:
    Levenberg–Marquardt), ``burn_in``, ``alpha``, ``memory``, ``initial`` and further
    ``options`` (``proposal``, ``ess_threshold``, ``rho_theta``, ``rtol``, ``atol``) are the
    :class:`ceemx.ParticleEM` options.

    Returns:
        A :class:`FitResult` whose history has :func:`fit`'s keys plus
        ``ParticleEM.history_keys`` (the PF log-likelihood estimate and the SAEM objective per
        epoch among them); ``states`` are the means of the last epoch's FFBSi draws.
    """
    kwargs = dict(
        n_particles=n_particles,
        n_smoothed=n_smoothed,
        burn_in=burn_in,
        alpha=alpha,
        memory=memory,
        initial=initial,
        **options,
    )
    if learner is not None:
        kwargs["learner"] = learner
    return fit(
        system,
        data,
        x_init,
        solver=ParticleEM(**kwargs),
        trainable=trainable,
        log_prior=log_prior,
        max_epochs=max_epochs,
        callbacks=callbacks,
        progress=progress,
        checkpoint=checkpoint,
        key=key,
    )
