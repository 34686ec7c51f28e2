"""``fit``: CE-EM (paper Algorithm 1) and the joint Gauss–Newton method, with history and checkpoints."""

from __future__ import annotations

import dataclasses
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import checkpoint as ckpt
from ._lm import RESULTS
from .data import Trajectories
from .learning.learners import AbstractLearner, LMLearner
from .learning.problem import trainable_mask
from .learning.step import make_problem, run_learner
from .models.system import AbstractSystem
from .objective import log_joint, nll_offset
from .smoothing.solver import LMSmoother, _smooth_batch, check_inputs

__all__ = ["EpochInfo", "FitResult", "fit"]


@dataclasses.dataclass
class EpochInfo:
    """What a callback receives after each epoch (or joint iteration).

    Attributes:
        epoch: 1-based epoch number.
        system: the system after this epoch.
        states: (B, T, n) states after this epoch.
        record: this epoch's history record (a dict; callbacks may add entries to it).
    """

    epoch: int
    system: AbstractSystem
    states: jax.Array
    record: dict


class FitResult(eqx.Module):
    """The outcome of :func:`fit`.

    Attributes:
        system: the learned system.
        states: (B, T, n) smoothed states at the learned θ.
        status: (B,) per-trajectory status codes (:class:`ceemx.RESULTS`) of the last smoothing.
        history: one dict per epoch: ``J`` (total log-likelihood, Eq. 9), ``J_per_trajectory``,
            ``dtheta_norm``, ``dx_norm``, ``smooth_time``, ``learn_time``, ``learner_steps``,
            ``smoother_steps`` and whatever callbacks added (e.g. ``eps``).
        converged: whether the stopping criterion on J was met (else ``max_epochs`` ran out).
        method: ``"alternate"`` or ``"joint"``.
        initial_J: J at the initial (x, θ).
    """

    system: AbstractSystem
    states: jax.Array
    status: jax.Array
    history: list = eqx.field(static=True)
    converged: bool = eqx.field(static=True)
    method: str = eqx.field(static=True)
    initial_J: float = eqx.field(static=True)

    @property
    def epochs(self) -> int:
        """Number of epochs (or joint iterations) run, including resumed ones."""
        return len(self.history)

    def history_array(self, name: str) -> np.ndarray:
        """One history entry across epochs as an array."""
        return np.asarray([h[name] for h in self.history])

    def messages(self) -> list[str]:
        """One status message per trajectory."""
        return [RESULTS(int(s)).message for s in np.asarray(self.status)]


class _Progress:
    def __init__(self, enabled: bool, total: int, initial: int):
        self.bar = None
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=initial, desc="CE-EM", unit="epoch", leave=True)

    def update(self, record):
        if self.bar is not None:
            self.bar.set_postfix(J=f"{record['J']:.6g}", t=f"{record['time']:.2f}s")
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()


_log_joint_jit = eqx.filter_jit(log_joint)


_offset_jit = eqx.filter_jit(nll_offset)


def _total_J(system, states, data, weights):
    J = np.asarray(_log_joint_jit(system, states, data))
    return float(np.sum(np.where(weights > 0, J, 0.0))), J


def _total_offset(system, data, weights) -> float:
    """Σ of −J's x-independent constants: J + offset is the scale of the relative tolerance."""
    return float(np.sum(np.where(weights > 0, np.asarray(_offset_jit(system, data)), 0.0)))


def fit(
    system: AbstractSystem,
    data: Trajectories,
    x_init=None,
    *,
    method: Literal["alternate", "joint"] = "alternate",
    smoother: LMSmoother | None = None,
    learner: AbstractLearner | None = None,
    trainable=None,
    rho_theta: float = 0.0,
    log_prior: Callable | None = None,
    max_epochs: int = 100,
    tol: float = 1e-10,
    atol: float = 0.0,
    callbacks: Sequence[Callable[[EpochInfo], Any]] = (),
    progress: bool | None = None,
    checkpoint: str | None = None,
    key=None,
    joint=None,
) -> FitResult:
    """Identify θ and the state trajectories by certainty-equivalent EM.

    ``method="alternate"`` is the paper's Algorithm 1: a smoothing step (Eq. 10, ``smoother``) and
    a learning step (Eq. 11, ``learner``) per epoch, until the improvement of J is at most
    ``tol·|J| + atol`` or ``max_epochs`` ran out. ``method="joint"`` minimises the same objective
    by Levenberg–Marquardt on (x, θ) together (see :class:`ceemx.JointLM`); one "epoch" is then one
    joint iteration.

    Args:
        system: the model at its initial θ.
        data: B observed trajectories.
        x_init: (B, T, n) initial states (``None``: :func:`ceemx.initialize.from_observations`).
        method: ``"alternate"`` (Algorithm 1) or ``"joint"``.
        smoother: smoothing-step solver (default :class:`LMSmoother`); its ``rho_x`` is ρ_x.
        learner: learning-step optimiser (default :class:`LMLearner`).
        trainable: which leaves learn (``None``: all model arrays except noise and prior; a
            callable ``where(system)`` or a boolean filter pytree).
        rho_theta: ρ_θ of Eq. 11.
        log_prior: optional ``system -> log p(θ)``.
        max_epochs: bound on epochs.
        tol, atol: stopping rule on the improvement of J per epoch: at most ``tol·|J + c| + atol``,
            c the noise models' normalising constants (so |J + c| = ½‖whitened residuals‖² for
            Gaussian noise, whatever the noise scales).
        callbacks: called with an :class:`EpochInfo` after every epoch; a dict returned by a
            callback is merged into that epoch's history record; returning ``False`` stops.
        progress: show a progress bar (``None``: only when stderr is a terminal).
        checkpoint: folder; after every epoch the state is written there atomically, and an
            existing checkpoint there is resumed from.
        key: PRNG key for stochastic learners (minibatches).
        joint: options of the joint method (a :class:`ceemx.JointLM`).

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError: on invalid inputs (before any compute).
    """
    from .initialize import from_observations

    smoother = LMSmoother() if smoother is None else smoother
    learner = LMLearner() if learner is None else learner
    key = jax.random.PRNGKey(0) if key is None else key
    if method not in ("alternate", "joint"):
        raise ValueError(f"`method` must be 'alternate' or 'joint'; got {method!r}.")
    if max_epochs < 0:
        raise ValueError(f"`max_epochs` must be >= 0; got {max_epochs}.")
    if rho_theta < 0:
        raise ValueError(f"`rho_theta` must be >= 0; got {rho_theta}.")
    if x_init is None:
        check_inputs(system, data)
        x_init = from_observations(system, data)
    check_inputs(system, data, x_init)

    states = jnp.asarray(x_init)
    # Strongly type the trainable arrays, as every later epoch's system (rebuilt from the learned θ)
    # has them: a weakly typed leaf (e.g. from jnp.asarray(10.0)) would otherwise make epoch 2
    # retrace the smoother and the learner.
    params, rest = eqx.partition(system, trainable_mask(system, trainable))
    params = jax.tree_util.tree_map(lambda a: a.astype(a.dtype) if eqx.is_array(a) else a, params)
    system = eqx.combine(params, rest)
    problem, theta = make_problem(
        system, states, data, trainable=trainable, rho_theta=rho_theta, log_prior=log_prior
    )
    weights = np.ones(data.batch_size)
    initial_J, J_traj = _total_J(system, states, data, weights)

    if method == "joint":
        from .joint import JointLM, joint_fit

        return joint_fit(
            system,
            data,
            states,
            joint if joint is not None else JointLM(rho_x=smoother.rho_x),
            trainable=trainable,
            rho_theta=rho_theta,
            log_prior=log_prior,
            max_iterations=max_epochs,
            tol=tol,
            atol=atol,
            callbacks=callbacks,
            progress=progress,
            checkpoint=checkpoint,
            initial_J=initial_J,
        )

    learner_state = learner.init(theta, key)
    history: list[dict] = []
    status = jnp.zeros((data.batch_size,), jnp.int32)
    if checkpoint is not None:
        loaded = ckpt.load(checkpoint, (theta, states, learner_state, status))
        if loaded is not None:
            (theta, states, learner_state, status), history = loaded
            system = problem.build(theta)
            weights = np.where(np.asarray(status) == RESULTS.nonfinite, 0.0, 1.0)
            J_traj = np.asarray(history[-1]["J_per_trajectory"])

    show = sys.stderr.isatty() if progress is None else progress
    bar = _Progress(show, max_epochs, len(history))
    converged = bool(history and history[-1].get("converged", False))
    stopped = bool(history and history[-1].get("stop", False))
    try:
        while len(history) < max_epochs and not (converged or stopped):
            epoch = len(history) + 1
            # J at the current (x, θ): the previous epoch's per-trajectory values, no recompute.
            J_before = float(np.sum(np.where(weights > 0, J_traj, 0.0)))

            t0 = time.perf_counter()
            sol = _smooth_batch(smoother, system, states, data, False)
            sol.states.block_until_ready()
            t_smooth = time.perf_counter() - t0
            status = sol.status
            failed = np.asarray(status) == RESULTS.nonfinite
            if failed.any():
                warnings.warn(
                    f"epoch {epoch}: smoothing failed (non-finite objective) on trajectories "
                    f"{np.flatnonzero(failed).tolist()}; they are excluded from learning.",
                    stacklevel=2,
                )
            weights = np.where(failed, 0.0, 1.0)
            dx = float(
                jnp.sqrt(jnp.sum(jnp.where(failed[:, None, None], 0.0, sol.states - states) ** 2))
            )
            new_states = sol.states

            t0 = time.perf_counter()
            problem, theta = make_problem(
                system,
                new_states,
                data,
                trainable=trainable,
                rho_theta=rho_theta,
                log_prior=log_prior,
                weights=weights,
            )
            theta_new, learner_state, info = run_learner(learner, problem, theta, learner_state)
            theta_new.block_until_ready()
            t_learn = time.perf_counter() - t0
            system = problem.build(theta_new)
            states = new_states

            J_after, J_traj = _total_J(system, states, data, weights)
            record = epoch_record(
                epoch, J_before, J_after, J_traj, theta_new - theta, dx, t_smooth, t_learn,
                info.steps, info.status, jnp.max(sol.iterations), failed,
            )  # fmt: skip
            improvement = J_after - J_before
            scale = abs(J_after + _total_offset(system, data, weights))  # J less its constants
            converged = bool(np.isfinite(J_after) and improvement <= tol * scale + atol)
            stopped = _close_epoch(
                history, record, EpochInfo(epoch, system, states, record), callbacks, bar,
                checkpoint, (theta_new, states, learner_state, status), converged,
            )  # fmt: skip
    finally:
        bar.close()
    return FitResult(system, states, status, history, converged, "alternate", initial_J)


def epoch_record(
    epoch, J_before, J_after, J_traj, dtheta, dx_norm, smooth_time, learn_time,
    learner_steps, learner_status, smoother_steps, failed, **extra,
) -> dict:  # fmt: skip
    """One history record (the keys :class:`FitResult` documents), as JSON-able Python values."""
    return {
        "epoch": epoch,
        "J_before": float(J_before),
        "J": float(J_after),
        "J_per_trajectory": np.asarray(J_traj).tolist(),
        "dtheta_norm": float(jnp.linalg.norm(dtheta)),
        "dx_norm": float(dx_norm),
        "smooth_time": smooth_time,
        "learn_time": learn_time,
        "time": smooth_time + learn_time,
        "learner_steps": int(learner_steps),
        "learner_status": int(learner_status),
        "smoother_steps": int(smoother_steps),
        "failed_trajectories": np.flatnonzero(failed).tolist(),
        **extra,
    }


def _close_epoch(
    history, record, info, callbacks, bar, checkpoint, tree, converged, halt=False
) -> bool:
    """Run callbacks, append the record, update the progress bar, checkpoint; returns "stop"."""
    stopped = _run_callbacks(callbacks, info) or halt
    record["converged"] = converged
    record["stop"] = converged or stopped
    history.append(record)
    bar.update(record)
    if checkpoint is not None:
        ckpt.save(checkpoint, tree, history)
    return stopped


def _run_callbacks(callbacks, info: EpochInfo) -> bool:
    stop = False
    for cb in callbacks:
        out = cb(info)
        if isinstance(out, dict):
            info.record.update(out)
        elif out is False:
            stop = True
    return stop
