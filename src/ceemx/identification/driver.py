"""``fit``: the one host-side driver that runs any fit solver.

The driver owns what every method needs — input validation, the initial states, dtype handling,
the epoch loop with its history, callbacks, progress bar, timing and atomic checkpoints with
resume — and delegates the mathematics to the solver object (:mod:`ceemx.identification.solvers`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jaxtyping import ArrayLike, PRNGKeyArray

from ceemx.data.checks import check_inputs, promote_inputs
from ceemx.data.sharding import resolve_devices, shard_batch
from ceemx.data.trajectories import Trajectories
from ceemx.identification.health import OUTLIER_OPTIONS, check_start, trajectory_health
from ceemx.identification.identifiability import Identifiability
from ceemx.identification.noise_check import NoiseCheck, NoiseCheckWarning, noise_check
from ceemx.identification.problem import FitProblem
from ceemx.identification.solvers.alternating import Alternating
from ceemx.identification.solvers.base import AbstractFitSolver, FitState, total_J
from ceemx.identification.solvers.laplace import LaplaceEM
from ceemx.identification.solvers.particle_em import ParticleEM
from ceemx.infra import checkpoint as ckpt
from ceemx.infra.compilation import BackgroundCompile, compile_in_background, has_idle_core
from ceemx.infra.distributed import is_main_process, to_host
from ceemx.infra.options import check_key
from ceemx.infra.runtime import one_blas_thread
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, codes, from_codes, messages, select
from ceemx.lib.tree import as_jax, trace_numbers
from ceemx.lib.typing import States, no_type_check
from ceemx.models.system import AbstractSystem

__all__ = ["EpochInfo", "FitResult", "fit", "particle_em", "precompile_fit"]


@dataclasses.dataclass
class EpochInfo:
    """What a callback receives after each epoch.

    Attributes:
        epoch: 1-based epoch number.
        system: the system after this epoch.
        states: (B, T, n) states after this epoch (in a multi-process fit a global array:
            read it with :func:`ceemx.infra.distributed.to_host`, on every process).
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
            a callback stopped the fit, or every trajectory failed). With ``identifiability``
            stopped, it means converged in what the data determine.
        solver: the solver that produced it.
        initial_J: J at the initial (x, θ) (over the trajectories fitted).
        excluded: indices of the trajectories the start-of-fit health test excluded
            (:mod:`ceemx.identification.health`); their states are returned as given, their status
            is ``outlier``, and ``history`` covers the others only.
        start_mean_square: (B,) the health test's r_b, the mean squared whitened residual of
            each trajectory at the start (``None`` with ``outliers="keep"``).
        identifiability: the parameter combinations the data do not determine, named
            (:class:`~ceemx.identification.identifiability.Identifiability`: ``message``,
            ``determined`` such as ``("a·b", "a·c")``, ``stopped``), as the solver found them —
            :class:`ceemx.JointLM` during the fit; :class:`ceemx.Alternating` and JointLM at the
            end point of a fit that did not converge in 20 epochs or more — else ``None``;
            :meth:`check_identifiability` runs the analysis on demand.
        problem: the :class:`~ceemx.identification.problem.FitProblem` that was fitted (the
            trajectories taking part; ``None`` for results built by hand).
        theta: the final flat θ in the problem's unconstrained coordinates.
        weights: the final (B',) trajectory weights of the fitted trajectories (0: failed).
        noise_rounds: with ``fit(..., noise="learn")``, one record per noise round (``round``,
            ``process_noise_std``, ``obs_noise_std``, ``log_evidence``, ``epochs``,
            ``converged``, ``change``; round 0 is the estimate at the start); else ``()``.
        noise_check: the end-of-fit noise check (:mod:`ceemx.identification.noise_check`): are
            the residuals consistent with the assumed noise? (``None`` with
            ``fit(..., diagnose=False)``, when no epoch ran, or for non-Gaussian noise.)
            :meth:`diagnostics` gives the full report.

    Parameter uncertainty (:mod:`ceemx.identification.uncertainty`): :meth:`covariance`,
    :meth:`standard_errors`, :meth:`parameter_estimates` — for the CE methods the Laplace
    approximation of the joint posterior p(x, θ | y) (valid at a converged maximum of J); for
    :class:`ceemx.LaplaceEM` the inverse observed information of the Laplace log-evidence, the
    states integrated out (learned noise scales included).
    """

    system: AbstractSystem
    states: States
    status: RESULTS
    history: list = eqx.field(static=True)
    converged: bool = eqx.field(static=True)
    solver: AbstractFitSolver
    initial_J: float = eqx.field(static=True)
    excluded: tuple = eqx.field(static=True, default=())
    start_mean_square: tuple | None = eqx.field(static=True, default=None)
    identifiability: Identifiability | None = eqx.field(static=True, default=None)
    problem: FitProblem | None = None
    theta: Any = None
    weights: Any = None
    noise_check: NoiseCheck | None = eqx.field(static=True, default=None)
    noise_rounds: tuple = eqx.field(static=True, default=())

    @property
    def epochs(self) -> int:
        """Number of epochs run, including resumed ones."""
        return len(self.history)

    def history_array(self, name: str) -> np.ndarray:
        """One history entry across epochs as an array."""
        return np.asarray([h[name] for h in self.history])

    def messages(self) -> list[str]:
        """One status message per trajectory, consistent with :attr:`converged`.

        A trajectory whose solver status is ``successful`` in a fit that did not converge (the
        epoch bound ran out, a callback stopped it) reads "stopped before convergence". When the
        end-of-fit noise check failed, its message follows the per-trajectory ones.
        """
        out = messages(self.status)
        if not self.converged:
            ok = np.atleast_1d(codes(self.status)).reshape(-1) == int(codes(RESULTS.successful))
            out = [
                "stopped before convergence (max_epochs reached or stopped by a callback)"
                if good
                else text
                for good, text in zip(ok, out, strict=True)
            ]
        if self.identifiability is not None:  # what the data do not determine, after them
            out = [*out, self.identifiability.message]
        if self.noise_check is not None and self.noise_check.message:
            out = [*out, self.noise_check.message]
        return out

    def diagnostics(self, **options):
        """Residual and noise diagnostics of the fitted model on the fitted trajectories.

        :func:`ceemx.identification.diagnostics.residual_diagnostics` at the end point (noise
        ratios and the noise the data say, the EKF prediction-error tests); ``options`` are its
        keyword arguments (``lags``, ``estimate``, ``factor``, ``initial``).
        """
        from ceemx.identification.diagnostics import residual_diagnostics

        problem, _, states, weights = self._laplace_inputs()
        keep = np.flatnonzero(np.asarray(weights) > 0)
        data = problem.data[keep] if keep.size < states.shape[0] else problem.data
        states = states[as_jax(keep)] if keep.size < states.shape[0] else states
        return residual_diagnostics(
            self.system, data, states, noise_check=self.noise_check, **options
        )

    def check_identifiability(self) -> Identifiability | None:
        """:attr:`identifiability`, or the analysis at the end point when the fit found none.

        One joint linearisation and Schur complement (compiled once per problem shape) and a host
        eigen-analysis (:mod:`ceemx.identification.identifiability`); ``None`` when the data
        determine every parameter.
        """
        from ceemx.identification.identifiability import identifiability_at

        if self.identifiability is not None:
            return self.identifiability
        problem, theta, states, weights = self._laplace_inputs()
        return identifiability_at(problem, theta, states, weights)

    def _laplace_inputs(self):
        if self.problem is None or self.theta is None:
            raise ValueError("This FitResult holds no problem: parameter uncertainty needs `fit`.")
        keep = np.setdiff1d(np.arange(self.states.shape[0]), np.asarray(self.excluded, int))
        states = self.states if not self.excluded else self.states[as_jax(keep)]
        weights = self.weights
        if weights is None:
            weights = jnp.ones(states.shape[0], states.dtype)
        return self.problem, self.theta, states, weights

    def covariance(self, natural: bool = False, *, hold_weak: bool = False):
        """(P, P) Laplace covariance of the trainable θ (:mod:`ceemx.identification.uncertainty`).

        Args:
            natural: ``False`` (default): of the flat θ in the problem's unconstrained
                coordinates (``FitResult.theta``); ``True``: in natural units by the delta method.
            hold_weak: for the CE methods, when some entries are not determined by the data,
                the covariance of the others with those held at their estimates (NaN in the held
                rows), instead of NaN everywhere (:meth:`summary` uses it).

        Returns:
            The covariance; all NaN, with a warning, when the Schur complement is not positive
            definite (not at a maximum, or a parameter is not identifiable).
        """
        from ceemx.identification.uncertainty import (
            evidence_covariance,
            natural_covariance,
            parameter_covariance,
        )

        problem, theta, states, weights = self._laplace_inputs()
        if isinstance(self.solver, LaplaceEM):
            cov = evidence_covariance(problem, theta, states, weights, self.solver.smoother)
        else:
            cov = parameter_covariance(problem, theta, states, weights, hold_weak=hold_weak)
        return natural_covariance(problem, theta, cov) if natural else cov

    def standard_errors(self):
        """Natural-unit standard errors (delta method), as a pytree like :attr:`system`.

        Each trainable leaf holds its standard errors (same shape); every other leaf is ``None``.
        """
        from ceemx.identification.uncertainty import standard_errors

        problem, theta, _, _ = self._laplace_inputs()
        return standard_errors(problem, theta, self.covariance())

    def parameter_estimates(self) -> dict[str, tuple[float, float]]:
        """``name → (estimate, standard error)`` per trainable scalar, in natural units.

        Names as written in the system (``sigma[0]``, ``A[0,1]``, ``process_noise.scale``); the
        key paths of earlier versions (``.A[0,1]``) still look up. The dict feeds
        :func:`ceemx.evaluation.report.estimate_table`.
        """
        from ceemx.identification.uncertainty import standard_errors_by_name

        problem, theta, _, _ = self._laplace_inputs()
        return standard_errors_by_name(problem, theta, self.covariance())

    def summary(
        self,
        format: Literal["text", "markdown"] = "text",
        *,
        level: float = 0.95,
        diagnostics: bool = False,
        uncertainty: bool = True,
        max_rows: int | None = 40,
    ) -> str:
        """What the fit found, for a person (:mod:`ceemx.identification.summary`).

        The trainable parameters in natural units, named as written (estimate, standard error,
        ``level`` interval, constraint), the noise models, J, data, epochs and time, status, the
        noise check and identifiability records, and the messages; ``diagnostics=True`` adds
        :meth:`diagnostics` (an EKF pass and a Laplace E-step, not run by default);
        ``uncertainty=False`` skips the covariance. ``format``: ``"text"`` or ``"markdown"``.

        Example:
            >>> print(result.summary())  # doctest: +SKIP
        """
        from ceemx.identification.summary import fit_summary

        return fit_summary(
            self,
            format,
            level=level,
            diagnostics=diagnostics,
            uncertainty=uncertainty,
            max_rows=max_rows,
        )

    def __repr__(self) -> str:
        """A few lines: solver, convergence, J and the first estimates (nothing computed)."""
        from ceemx.identification.summary import short_repr

        return short_repr(self)


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


@one_blas_thread  # XLA's LAPACK calls in one BLAS thread (ceemx.infra.runtime)
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
    checkpoint_mismatch: Literal["raise", "restart"] = "raise",
    key: PRNGKeyArray | None = None,
    outliers: str = "exclude",
    devices: Literal["all"] | Mesh | None = None,
    diagnose: bool = True,
    noise: Literal["fixed", "learn"] = "fixed",
) -> FitResult:
    """Identify θ and the state trajectories by maximising the CE-EM objective J(x, θ) (Eq. 9).

    Args:
        system: the model at its initial θ.
        data: B observed trajectories.
        x_init: (B, T, n) initial states (``None``: the solver's ``initial_states`` —
            :func:`ceemx.identification.initialize.warm_start`, least squares through the
            observation map and a smoothing pass at the initial θ, for the CE methods).
        solver: the method — :class:`ceemx.Alternating` (the paper's Algorithm 1, default),
            :class:`ceemx.JointLM` (joint Levenberg–Marquardt on (x, θ)) or
            :class:`ceemx.ParticleEM` (particle filter + FFBSi + SAEM) or
            :class:`ceemx.LaplaceEM` (EM with a Gaussian E-step; learns noise covariances); its
            tolerances decide convergence.
        trainable: which leaves learn (``None``: all model arrays except noise and prior; a
            callable ``where(system)`` or a boolean filter pytree). Noise models may be selected
            only with :class:`ceemx.LaplaceEM`.
        log_prior: optional ``system -> log p(θ)``.
        max_epochs: bound on epochs (iterations of the solver).
        callbacks: called with an :class:`EpochInfo` after every epoch; a dict returned by a
            callback is merged into that epoch's history record; returning ``False`` stops.
        progress: show a progress bar (``None``: only when stderr is a terminal).
        checkpoint: folder; after every epoch the state is written there atomically, and an
            existing checkpoint there is resumed from — only if it was written by the same fit
            (data, system, method and options; see ``docs/guarantees.md``). The folder must be
            writable (checked before any compute); the fit holds it alone, by a lock on its
            ``.lock`` file, until it returns.
        checkpoint_mismatch: what to do with a checkpoint that is another fit's, corrupt, or not
            finite: ``"raise"`` a :class:`ceemx.infra.checkpoint.CheckpointError` naming what
            differs, or ``"restart"`` (warn, start afresh, overwrite it).
        key: PRNG key for stochastic solvers and learners (default ``PRNGKey(0)``).
        outliers: the start-of-fit health test (:mod:`ceemx.identification.health`): ``"exclude"``
            (default) fits without the trajectories whose residuals are far outside the noise model
            compared with the others, naming them in a warning and in
            :attr:`FitResult.excluded` (their states are returned as given, status
            ``outlier``); ``"warn"`` only names them; ``"keep"`` skips the test.
        devices: data parallelism over the trajectories (:mod:`ceemx.data.sharding`): ``None``
            (default) places nothing; ``"all"`` splits the batch axis of the data and states over
            all visible devices, a 1-D :class:`jax.sharding.Mesh` over its devices. When B is
            not divisible by the device count the largest divisor of B devices is used. Results
            agree with ``None`` to rounding; with one device it changes nothing. Over several
            processes (:mod:`ceemx.infra.distributed`) every process passes the same whole data
            set, B must be a multiple of the device count, only process 0 shows progress and
            writes ``checkpoint``, callbacks see the states as a global array, and every
            process gets the whole result.
        diagnose: the end-of-fit noise check (:mod:`ceemx.identification.noise_check`, one
            pass over the residuals): warns when the residuals are inconsistent with the assumed
            noise (too tight or too loose by more than 2× in standard deviation) and stores it in
            :attr:`FitResult.noise_check`; ``False`` skips it.
        noise: ``"fixed"`` (default) fits at the system's noise models; ``"learn"`` learns one
            factor on each — process and observation noise — from the data, for a user who does
            not know the noise scales: CE fits alternated with the maximiser of the Laplace
            log-evidence in the two factors, until they settle
            (:func:`ceemx.identification.noise.fit_learning_noise`; the noise models' shape is
            kept; ``FitResult.noise_rounds`` records the rounds; ``max_epochs`` bounds each
            round's fit; not with ``checkpoint``). For the CE solvers (:class:`ceemx.Alternating`,
            :class:`ceemx.JointLM`); :class:`ceemx.LaplaceEM` learns noise through
            ``trainable``.

    Returns:
        A :class:`FitResult`.

    Raises:
        ValueError, TypeError: on invalid inputs (before any compute).
        ceemx.infra.checkpoint.CheckpointError: (a ``ValueError``) for an unwritable ``checkpoint``
            folder or one another fit is writing (before any compute), or a checkpoint that
            cannot be resumed (see above).

    Example:
        >>> result = ceemx.fit(guess, data, solver=ceemx.JointLM(), trainable=lambda s: s.rho)
        ... # doctest: +SKIP
    """
    if noise != "fixed":
        return _fit_learning_noise(noise, solver, system, data, x_init, locals())
    if outliers not in OUTLIER_OPTIONS:
        raise ValueError(f"`outliers` must be one of {OUTLIER_OPTIONS}; got {outliers!r}.")
    with contextlib.ExitStack() as hold:  # the checkpoint folder's lock, for the whole fit
        solver, data, states, key, max_epochs, spread, compiling = _prepare(
            system,
            data,
            x_init,
            solver,
            max_epochs,
            checkpoint,
            checkpoint_mismatch,
            key,
            devices,
            hold,
            trainable,
            log_prior,
        )
        problem, theta = FitProblem.create(system, data, trainable=trainable, log_prior=log_prior)
        all_states = states
        excluded, health = _screen_outliers(problem, theta, states, outliers)
        check_start(problem, theta, states, health, excluded)  # refuses absurd or non-finite starts
        if excluded.any():
            keep = np.flatnonzero(~excluded)
            data, states = data[keep], states[keep]
            problem, theta = FitProblem.create(
                system, data, trainable=trainable, log_prior=log_prior
            )

        state = solver.init(problem, theta, states, key)
        initial_J = total_J(state)
        history: list[dict] = []
        fingerprint = None
        if checkpoint is not None:
            template, local = dataclasses.replace(state, cache=None), problem
            if spread:  # fingerprint and load on gathered arrays (a resumed state is local)
                template = _local(template)
                local = _local_problem(problem, system, trainable, log_prior)
            fingerprint = ckpt.fingerprint(template, local, theta, solver)
            loaded = ckpt.load(checkpoint, template, fingerprint, mismatch=checkpoint_mismatch)
            if loaded is not None:
                state, history = loaded

        if compiling is not None:  # the epoch programs compiled beside the start states
            compiling.join()
        state, converged = _run_epochs(
            solver,
            problem,
            state,
            history,
            max_epochs,
            callbacks,
            progress,
            checkpoint,
            fingerprint,
            spread,
        )
        if spread:  # the rest runs on every process alike, on gathered arrays (the result)
            state, all_states = _local(dataclasses.replace(state, cache=None)), _local(all_states)
            problem = _local_problem(problem, system, trainable, log_prior)
        state = solver.postprocess(problem, state)
        # Never "converged" when no trajectory took part or J is not finite.
        took_part = bool(np.any(np.asarray(state.weights) > 0))
        converged = bool(converged and took_part and np.isfinite(total_J(state)))
        found = solver.identifiability(problem, state, history, converged) if took_part else None
        out_states, status = _with_excluded(state, all_states, excluded)
        check = _check_noise(problem, solver, state, converged) if diagnose and history else None
        return FitResult(
            problem.build(state.theta),
            out_states,
            status,
            history,
            converged,
            solver,
            initial_J,
            tuple(int(b) for b in np.flatnonzero(excluded)),
            None if health is None else tuple(float(r) for r in health.mean_square),
            problem=problem,
            theta=state.theta,
            weights=state.weights,
            identifiability=found,
            noise_check=check,
        )


def _fit_learning_noise(noise, solver, system, data, x_init, arguments: dict) -> FitResult:
    """``fit(..., noise="learn")``: validated here, run by the noise module's rounds."""
    if noise != "learn":
        raise ValueError(f"`noise` must be 'fixed' or 'learn'; got {noise!r}.")
    if solver is not None and (solver.learns_noise or isinstance(solver, ParticleEM)):
        raise ValueError(
            f"fit(..., noise='learn') alternates certainty-equivalent fits (Alternating, "
            f"JointLM) with noise estimates; {type(solver).__name__} is not one. LaplaceEM "
            "learns noise itself: pass trainable=lambda s: (..., s.process_noise, s.obs_noise)."
        )
    from ceemx.identification.noise import fit_learning_noise

    options = {k: v for k, v in arguments.items() if k not in ("system", "data", "x_init", "noise")}
    return fit_learning_noise(system, data, x_init, **options)


def _prepare(
    system,
    data,
    x_init,
    solver,
    max_epochs,
    checkpoint,
    checkpoint_mismatch,
    key,
    devices,
    hold,
    trainable,
    log_prior,
):
    """Validate the inputs (before any compute); the solver, data and start states to fit.

    The checkpoint folder's lock is entered into the exit stack ``hold``: held until the fit ends.
    The last value returned is the thread compiling the solver's epoch programs while the start
    states are computed (:meth:`AbstractFitSolver.precompile`; ``None`` when there is none):
    join it before the first epoch.
    """
    solver = Alternating() if solver is None else solver
    if not isinstance(solver, AbstractFitSolver):
        raise TypeError(
            f"`solver` must be a fit solver such as ceemx.Alternating() or ceemx.JointLM(); "
            f"got {solver!r}."
        )
    max_epochs = _check_max_epochs(max_epochs)
    if key is not None:
        check_key(key)
    mesh = resolve_devices(devices)
    spread = mesh is not None and mesh.is_multi_process  # data over several processes' devices
    if spread and isinstance(solver, LaplaceEM | ParticleEM):
        raise ValueError(
            f"`devices` spans {jax.process_count()} processes: a multi-process fit runs "
            f"ceemx.JointLM or ceemx.Alternating; {type(solver).__name__} reads per-trajectory "
            "values on the host that are not gathered across processes. Fit it in one process "
            "(devices=None, or a mesh of jax.local_devices())."
        )
    if checkpoint is not None:
        ckpt.check_folder(checkpoint, checkpoint_mismatch)
        if not spread or is_main_process():  # process 0 alone writes a multi-process fit's
            hold.enter_context(ckpt.lock(checkpoint))
    given = system  # fit builds its problem from the system as given
    system, data, x_init = promote_inputs(system, data, x_init)
    check_inputs(system, data)
    if x_init is not None:
        check_inputs(system, data, x_init)
    # What the problem refuses (trainable leaves, noise a solver cannot learn), before any compute.
    solver.check_problem(*FitProblem.create(given, data, trainable=trainable, log_prior=log_prior))
    dtype = data.y.dtype  # the working dtype (promote_inputs)
    compiling = None
    if (
        mesh is None
        and type(solver).precompile is not AbstractFitSolver.precompile
        and has_idle_core()  # a second compiling thread on a busy machine only competes
    ):
        compiling = _precompile(
            trace_numbers(solver, dtype), given, data, x_init, trainable, log_prior
        )
    if x_init is None:
        x_init = solver.initial_states(system, data)
        check_inputs(system, data, x_init)
    states = as_jax(x_init)
    if mesh is not None:
        data, states = shard_batch(data, states, mesh)
    solver = trace_numbers(solver, states.dtype)
    key = jax.random.PRNGKey(0) if key is None else key
    return solver, data, states, key, max_epochs, spread, compiling


def _local(tree):
    """``tree`` with every array gathered onto this process (after a multi-process fit)."""
    return jax.tree.map(lambda a: as_jax(to_host(a)) if eqx.is_array(a) else a, tree)


def _local_problem(problem: FitProblem, system, trainable, log_prior) -> FitProblem:
    """``problem`` over this process's copy of its data (gathered: a multi-process fit's)."""
    return FitProblem.create(
        system, _local(problem.data), trainable=trainable, log_prior=log_prior
    )[0]


def precompile_fit(
    system: AbstractSystem,
    data: Trajectories,
    x_init: ArrayLike | None = None,
    *,
    solver: AbstractFitSolver | None = None,
    trainable=None,
    log_prior: Callable[[AbstractSystem], Any] | None = None,
) -> BackgroundCompile:
    """Start compiling the epoch programs of the same :func:`fit` call, in a background thread.

    :func:`fit` does this itself while it computes the start states; call this when the start
    states or the data come from your own work first (a warm start, loading, simulation), so the
    compiler runs meanwhile on another core, then ``join()`` the thread before calling
    :func:`fit` with the same ``system``, ``data`` shapes, ``solver``, ``trainable`` and
    ``log_prior``. ``x_init`` may be ``None`` (the programs depend only on the states' shape and
    dtype). Nothing is computed: only :meth:`AbstractFitSolver.precompile` (no-op for solvers
    without one). Arguments are validated as by :func:`fit`.

    Returns:
        The started :class:`~ceemx.infra.compilation.BackgroundCompile`; its ``join()`` runs
        the jobs the worker has not started yet in the calling thread, then waits for the worker.
    """
    solver = Alternating() if solver is None else solver
    if not isinstance(solver, AbstractFitSolver):
        raise TypeError(f"`solver` must be a fit solver; got {solver!r}.")
    given = system
    system, data, x_init = promote_inputs(system, data, x_init)
    check_inputs(system, data)
    if x_init is not None:
        check_inputs(system, data, x_init)
    return _precompile(
        trace_numbers(solver, data.y.dtype), given, data, x_init, trainable, log_prior
    )


def _precompile(solver, system, data, x_init, trainable, log_prior):
    """Start compiling the solver's epoch programs in a background thread (returned).

    The problem and θ are those :func:`fit` builds next; without ``x_init`` the states are
    zeros of the start states' shape and dtype (the programs depend on those alone).
    """
    problem, theta = FitProblem.create(system, data, trainable=trainable, log_prior=log_prior)
    if x_init is None:
        B, T, _ = data.y.shape
        states = jnp.zeros((B, T, system.state_dim), data.y.dtype)
    else:
        states = as_jax(x_init)
    return compile_in_background(solver.precompile(problem, theta, states))


def _screen_outliers(problem: FitProblem, theta, states, outliers: str):
    """The start-of-fit health test: (trajectories to exclude, the health record or ``None``)."""
    excluded = np.zeros((problem.data.batch_size,), bool)
    if outliers == "keep":
        return excluded, None
    health = trajectory_health(problem, theta, states)
    if not np.any(np.isfinite(health.mean_square)):
        raise ValueError(
            "no trajectory has a finite objective at the start: check the model's "
            "parameters and noise, the inputs and `x_init` (J is not finite for all "
            f"{problem.data.batch_size} trajectories)."
        )
    bad = health.flagged & np.isfinite(health.mean_square)
    if bad.any():
        idx = np.flatnonzero(bad)
        action = "excluded from the fit" if outliers == "exclude" else "kept (outliers='warn')"
        warn(
            f"trajectories {health.describe(idx)} have residuals far outside the noise model "
            f"(mean squared whitened residual; median {health.median:.3g}): {action}. "
            "Pass outliers='keep' to skip this test (ceemx.identification.health)."
        )
        if outliers == "exclude":
            excluded = bad
    return excluded, health


def _check_noise(problem: FitProblem, solver, state: FitState, converged: bool):
    """The end-of-fit noise check (:mod:`ceemx.identification.noise_check`); warns on failure."""
    learned = tuple(f for f in ("process_noise", "obs_noise") if problem.trains(f))
    check = noise_check(
        problem.build(state.theta),
        problem.data,
        state.states,
        weights=state.weights,
        n_params=int(np.size(state.theta)),
        learned=learned,
        converged=converged,
    )
    if check is not None and check.message:
        warn(check.message, NoiseCheckWarning)
    return check


def _run_epochs(
    solver,
    problem,
    state,
    history,
    max_epochs,
    callbacks,
    progress,
    checkpoint,
    fingerprint,
    spread,
):
    """The epoch loop: step, record, stop rule, callbacks, progress, checkpoints (into history).

    Over several processes (``spread``) only process 0 shows progress and writes checkpoints.
    """
    show = (sys.stderr.isatty() if progress is None else progress) and is_main_process()
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
                saved = dataclasses.replace(state, cache=None)
                saved = _local(saved) if spread else saved  # a collective: every process
                if not spread or is_main_process():
                    ckpt.save(checkpoint, saved, history, fingerprint)
    finally:
        bar.close()
    return state, converged


def _with_excluded(state: FitState, all_states, excluded: np.ndarray):
    """States and statuses of every trajectory: the excluded ones as given, status ``outlier``."""
    if not excluded.any():
        return state.states, state.status
    keep = as_jax(np.flatnonzero(~excluded))
    out_states = all_states.at[keep].set(state.states)
    codes_all = np.full(excluded.shape, -1)
    codes_all[~excluded] = np.asarray(codes(state.status)).reshape(-1)
    status = select(as_jax(excluded), RESULTS.outlier, from_codes(np.maximum(codes_all, 0)))
    return out_states, status


def _record(epoch: int, before: FitState, after: FitState, elapsed: float, own: dict) -> dict:
    """The driver's history keys (see :class:`FitResult`) and the solver's own."""
    ok = to_host(after.weights) > 0
    dx = np.where(ok[:, None, None], to_host(after.states) - to_host(before.states), 0.0)
    return {
        "epoch": epoch,
        "J_before": total_J(before),
        "J": total_J(after),
        "J_per_trajectory": to_host(after.J).tolist(),
        "dtheta_norm": float(np.linalg.norm(to_host(after.theta) - to_host(before.theta))),
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
    checkpoint_mismatch: str = "raise",
    outliers: str = "exclude",
    diagnose: bool = True,
    **options: Any,
) -> FitResult:
    """Particle EM (fully adapted particle filter, FFBSi, SAEM): ``fit`` with :class:`ParticleEM`.

    ``system``, ``data``, ``trainable``, ``log_prior``, ``max_epochs``, ``callbacks``,
    ``progress``, ``checkpoint``, ``key``, ``checkpoint_mismatch``, ``outliers`` and ``diagnose``
    are as for :func:`fit`; ``x_init`` only sets the
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
        checkpoint_mismatch=checkpoint_mismatch,  # pyright: ignore[reportArgumentType]
        outliers=outliers,
        diagnose=diagnose,
    )
