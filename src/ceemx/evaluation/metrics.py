"""Metrics of identified models: ε(θ) (Eq. 14), simulation RMSE, benchmark scores, mean (SE).

- :func:`dynamics_error` — the paper's ε(θ) as the authors computed it: the mean squared difference
  of the continuous-time vector fields of two systems at 1024 random states.
- :func:`simulation_rmse` — noise-free open-loop rollouts compared with the observations.
- :func:`benchmark_score` — the official ``nonlinear-benchmarks`` protocol on measured test
  records: initial state from the first ``n_init`` outputs, free run, RMSE / NRMSE / fit %
  (a :class:`BenchmarkScore`).
- :func:`mean_se` — mean and standard error over seeds (an :class:`Estimate`; defined in
  :mod:`ceemx.evaluation.estimates`, which the reports read too).
- Fit callbacks and checks: :class:`DynamicsErrorCallback` (ε(θ) every epoch),
  :class:`FitTimer` (wall time every epoch), :func:`is_monotone` (J never decreased).

Tables, files and figures are in :mod:`ceemx.evaluation.report`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ceemx.data.checks import prepare, promote_array
from ceemx.data.trajectories import Trajectories, rollout_one
from ceemx.evaluation.estimates import Estimate, mean_se  # the seeds' summaries, here too
from ceemx.evaluation.initial_state import initial_state_prepared
from ceemx.evaluation.simulation import free_run_batch, strongly_typed
from ceemx.infra.compilation import jit
from ceemx.infra.policy import Runs, program
from ceemx.infra.progress import task
from ceemx.infra.warn import warn
from ceemx.lib.results import RESULTS, select
from ceemx.lib.tree import as_jax
from ceemx.lib.typing import ObservationMask, Observations, States, no_type_check
from ceemx.models.system import AbstractContinuousSystem, AbstractSystem, float_dtype

__all__ = [
    "BenchmarkScore",
    "DynamicsErrorCallback",
    "Estimate",
    "FitTimer",
    "SimulationRMSE",
    "benchmark_score",
    "dynamics_error",
    "is_monotone",
    "mean_se",
    "simulation_rmse",
]


# --------------------------------------------------------------------------------------------
# ε(θ), Eq. 14
# --------------------------------------------------------------------------------------------


@jit
def _dynamics_error(system, true_system, key, mean, std, num: int):
    n = mean.shape[0]
    x = mean[None, :] + std * jax.random.normal(key, (num, n), mean.dtype)
    u = jnp.zeros((0,), mean.dtype)
    t = jnp.zeros((), mean.dtype)

    def field(s):
        return jax.vmap(lambda xi: s.vector_field(xi, u, t))(x)

    return jnp.mean((field(system) - field(true_system)) ** 2)


def dynamics_error(
    system: AbstractContinuousSystem,
    true_system: AbstractContinuousSystem,
    *,
    key=None,
    num: int = 1024,
    mean=None,
    std: float = 5.0,
) -> Float[Array, ""]:
    r"""ε(θ) of paper Eq. 14, exactly as the authors' code computes it.

    ε(θ) = mean over the ``num``·n entries of (F_θ(x) − F_θtrue(x))², x ~ N(mean, std²·I), where
    F is the continuous-time vector field (``system.vector_field(x, u, 0)`` with an empty input)
    — a mean squared error with no square root (the paper's Eq. 14 writes an expected norm; the
    authors' code, whose numbers the paper's Figure 3 shows, uses ``mse_loss`` on the derivatives).

    Args:
        system: the estimated system.
        true_system: the reference system (same state dimension).
        key: PRNG key of the state samples (default ``PRNGKey(4)``, fixed so that ε is comparable
            across epochs, runs and methods).
        num: number of sampled states (authors: 1024).
        mean: (n,) mean of the sampled states; default: ``true_system.default_state_mean()``
            (for :class:`~ceemx.systems.CoupledLorenz` the paper's initial-state mean, (−6, −6, 24)
            per attractor); required for systems without one.
        std: standard deviation of the sampled states (authors: 5).

    Returns:
        A scalar in the systems' dtype.

    Raises:
        ValueError: when ``mean`` is needed but not given, or has the wrong shape.

    Compiled once per system structure and ``num``; safe to call every epoch.

    """
    if mean is None:
        mean = true_system.default_state_mean()
        if mean is None:
            raise ValueError(
                f"`mean` is required for {type(true_system).__name__} "
                "(no default sampling distribution)."
            )
    dtype = float_dtype(true_system)
    mean = jnp.asarray(mean, dtype)
    if mean.shape != (true_system.state_dim,):
        raise ValueError(f"`mean` must have shape ({true_system.state_dim},); got {mean.shape}.")
    key = jax.random.PRNGKey(4) if key is None else key
    return _dynamics_error(system, true_system, key, mean, jnp.asarray(std, dtype), int(num))


# --------------------------------------------------------------------------------------------
# Open-loop simulation
# --------------------------------------------------------------------------------------------


class SimulationRMSE(NamedTuple):
    """RMSE of noise-free open-loop predictions of the observations.

    Attributes:
        per_trajectory: (B,) RMSE over each trajectory's observed entries.
        overall: RMSE over all observed entries of the batch.
        predictions: (B, T, m) predicted observations.

    """

    per_trajectory: Array
    overall: Array
    predictions: Array


@jit
def _simulate_obs(system, x1, u):
    def one(x0, ub):
        xs = rollout_one(system, x0, ub)
        ts = jnp.arange(ub.shape[0])
        return jax.vmap(system.observe)(xs, ub, ts)

    return jax.vmap(one)(x1, u)


def simulation_rmse(
    system: AbstractSystem, data: Trajectories, x1: Float[Array, "B n"]
) -> SimulationRMSE:
    """Open-loop (noise-free) rollouts from ``x1`` compared with ``data.y`` over observed entries.

    Args:
        system: the model.
        data: B observed trajectories (masked entries are ignored).
        x1: (B, n) initial states of the rollouts.

    Returns:
        A :class:`SimulationRMSE` (per trajectory, overall, and the predictions).

    """
    x1 = jnp.asarray(x1, data.y.dtype)
    if x1.shape != (data.batch_size, system.state_dim):
        raise ValueError(
            f"`x1` must have shape (B, n) = {(data.batch_size, system.state_dim)}; got {x1.shape}."
        )
    pred = _simulate_obs(system, x1, data.u)
    per, overall = _rmse(pred, data.y, data.mask)
    return SimulationRMSE(per, overall, pred)


@program(runs=Runs.ONCE)  # on the host: one program, where op by op it compiled a dozen small ones
def _rmse(pred, y, mask):
    """(per-trajectory, overall) RMSE of ``pred`` against ``y`` over the entries of ``mask``."""
    sq = jnp.where(mask, (pred - y) ** 2, 0.0)
    count = jnp.sum(mask, axis=(1, 2), dtype=sq.dtype)
    per = jnp.sqrt(jnp.sum(sq, axis=(1, 2)) / jnp.maximum(count, 1))
    overall = jnp.sqrt(jnp.sum(sq) / jnp.maximum(jnp.sum(count), 1))
    return per, overall


# --------------------------------------------------------------------------------------------
# The nonlinear-benchmarks protocol
# --------------------------------------------------------------------------------------------


class BenchmarkScore(NamedTuple):
    """Scores of free-run simulations of B test trajectories (:func:`benchmark_score`).

    Per trajectory b and output j, over the N present entries of y[n_init:], with errors
    e = s_j (ŷ − y) in scaled units (``scale``):

    Attributes:
        rmse: (B, m) sqrt(Σ e² / N).
        nrmse: (B, m) RMSE / std(y), the standard deviation (ddof 0, scaled) of the scored
            outputs; NaN for a constant output (one value: no spread to compare with; warned,
            status ``constant_output``).
        fit_percent: (B, m) 100·(1 − ‖y − ŷ‖ / ‖y − ȳ‖) = 100·(1 − NRMSE).
        rmse_overall: (B,) RMSE over all scored entries of the trajectory (every output).
        nrmse_overall: (B,) mean over outputs of ``nrmse``.
        fit_percent_overall: (B,) mean over outputs of ``fit_percent``.
        y_sim: (B, T, m) simulated outputs over the whole record (unscaled).
        x_sim: (B, T, n) simulated states (``x_sim[:, 0]`` is ``x1``).
        x1: (B, n) initial states of the simulations.
        status: (B,) :class:`ceemx.RESULTS` of the initial-state estimation (``successful``
            where ``x1`` was given; ``nonfinite`` where x̂₁ is not finite), or ``diverged`` where
            the free run from a finite x̂₁ is not finite (its scores are NaN or inf; warned), or
            ``constant_output`` where a scored output of the record is constant (its NRMSE and
            fit % are NaN; warned).
        n_init: outputs used for the initial state (not scored).
        outputs: the outputs' labels from the test data's ``info`` (``name [unit]``; the unit
            only when the errors are not scaled), which the table prints; ``None``: ``y1``, ….
    """

    rmse: Float[Array, "B m"]
    nrmse: Float[Array, "B m"]
    fit_percent: Float[Array, "B m"]
    rmse_overall: Float[Array, " B"]
    nrmse_overall: Float[Array, " B"]
    fit_percent_overall: Float[Array, " B"]
    y_sim: Observations
    x_sim: States
    x1: Float[Array, "B n"]
    status: RESULTS
    n_init: int
    outputs: tuple[str, ...] | None = None

    def table(
        self,
        *,
        output_names: Sequence[str] | None = None,
        unit: str = "",
        format: str = "text",
        arrays: bool = False,
    ) -> str:
        """RMSE / NRMSE / fit % per record and output in a few lines (``repr`` of the score).

        The trajectories (``y_sim``, ``x_sim``, ``x1``) only with ``arrays=True``; ``unit``
        labels the RMSE (e.g. ``"mV"`` with a dataset's ``score_scale``); ``format``:
        ``"text"`` or ``"markdown"`` (:func:`ceemx.evaluation.report.score_table`).
        """
        from ceemx.evaluation.report import score_table

        return score_table(self, output_names=output_names, unit=unit, format=format, arrays=arrays)

    def __repr__(self) -> str:
        """The score in a few lines, no arrays (:meth:`table`)."""
        return self.table()

    __str__ = __repr__


@jit
def score_batch(
    y: Observations,
    y_sim: Observations,
    mask: ObservationMask,
    n_init: Int[Array, ""],
    scale: Float[Array, " m"],
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """RMSE, NRMSE, fit % per output, then overall, on steps ≥ ``n_init`` (see BenchmarkScore)."""
    m = mask & (jnp.arange(y.shape[1]) >= n_init)[None, :, None]
    scale = scale[None, None, :]
    count = jnp.sum(m, axis=1, dtype=y.dtype)  # (B, m)
    safe = jnp.maximum(count, 1)
    sq = jnp.where(m, (scale * (y_sim - y)) ** 2, 0.0)
    rmse = jnp.sqrt(jnp.sum(sq, axis=1) / safe)
    mean = jnp.sum(jnp.where(m, y, 0.0), axis=1) / safe
    dev = jnp.where(m, (scale * (y - mean[:, None, :])) ** 2, 0.0)
    nrmse = rmse / jnp.sqrt(jnp.sum(dev, axis=1) / safe)
    overall = jnp.sqrt(jnp.sum(sq, axis=(1, 2)) / jnp.maximum(jnp.sum(count, axis=1), 1))
    fit = 100.0 * (1.0 - nrmse)
    return rmse, nrmse, fit, overall, jnp.mean(nrmse, axis=1), jnp.mean(fit, axis=1)


@no_type_check  # validates its arguments
def benchmark_score(
    system: AbstractSystem,
    test: Trajectories,
    n_init: int,
    *,
    scale: ArrayLike | None = None,
    x1: ArrayLike | None = None,
    **kwargs,
) -> BenchmarkScore:
    """Score ``system`` on test records by the official ``nonlinear-benchmarks`` protocol.

    1. x̂₁ from the first ``n_init`` test outputs and the inputs
       (:func:`ceemx.evaluation.initial_state.estimate_initial_state`);
    2. a noise-free :func:`ceemx.evaluation.simulation.free_run` from x̂₁ over the whole test input;
    3. RMSE, NRMSE = RMSE / std(y) and fit % = 100·(1 − ‖y − ŷ‖/‖y − ȳ‖) on ``y[n_init:]``, per
       output and overall (masked entries left out), as ``nonlinear_benchmarks.error_metrics``.

    Args:
        system: the identified model, in the data's units (a model fitted on normalised data
            scores normalised test data; pass the output standard deviations as ``scale``).
        test: B test records (pad records of different lengths and mask the padding).
        n_init: outputs a model may use to set its state, in [1, T−1] (a dataset's ``n_init``).
        scale: (m,) or scalar factors applied to the errors (1000 for Silverbox's mV — a
            dataset's ``score_scale`` — or the ``y_std`` of normalised data); NRMSE and fit %
            do not depend on it. ``None``: 1.
        x1: (B, n) initial states to use instead of estimating them.
        **kwargs: options of :func:`~ceemx.evaluation.initial_state.estimate_initial_state`
            (``refine``, ``smoother``, ``warm_process_noise``).

    ``test`` and ``x1`` are cast to the dtype of the system's parameters, as by
    :func:`ceemx.fit` and :func:`ceemx.smooth` (:func:`ceemx.data.checks.prepare`).

    Returns:
        A :class:`BenchmarkScore` (arrays in the system's dtype).

    Raises:
        TypeError: wrong argument types.
        ValueError: before any compute: ``n_init`` outside [1, T−1], mismatched shapes, a
            float16 system, non-finite data or ``x1``, a bad ``scale``, or a trajectory with no
            observed output in its window or in its scored part.

    Compiled once per system structure, B, T and ``n_init`` (the initial-state window, see
    :func:`~ceemx.evaluation.initial_state.estimate_initial_state`); parameters and data are traced.

    Example:
        >>> ds = ceemx.datasets.silverbox()  # doctest: +SKIP
        >>> test = ds.tests["multisine"]  # doctest: +SKIP
        >>> s = benchmark_score(model, test, ds.n_init, scale=ds.score_scale)  # doctest: +SKIP
        >>> float(s.rmse[0, 0])  # in mV  # doctest: +SKIP
    """
    if not isinstance(system, AbstractSystem):
        raise TypeError(f"`system` must be a ceemx.AbstractSystem; got {type(system).__name__}.")
    inputs = prepare(system, test)  # one dtype, the system's, as fit and smooth
    system, test = inputs.system, inputs.data
    x1 = promote_array("x1", x1, system)
    n_init = _check_record(test, n_init)
    s = _check_scale(scale, system.obs_dim)
    records = f"{test.batch_size} record{'s' if test.batch_size > 1 else ''}"
    with task(f"benchmark_score: {records} of {test.num_steps} steps"):  # a line when it runs long
        if x1 is None:
            start, status = initial_state_prepared(
                system, test, n_init, return_status=True, **kwargs
            )
        else:
            start, status = _given_start(x1, system, test, kwargs)
        zero = as_jax(np.zeros((), np.int32))  # host values transferred: no program per shape
        x_sim, y_sim = free_run_batch(strongly_typed(system), start, test.u, zero)
        scale_arr = as_jax(np.asarray(np.broadcast_to(s, (system.obs_dim,)), test.y.dtype))
        metrics = score_batch(test.y, y_sim, test.mask, jnp.asarray(n_init), scale_arr)
        status = _flag_diverged(start, metrics[3], status)
        metrics, status = _flag_constant(test, n_init, metrics, status)
    info = test.info  # the outputs' names, with their units where the errors are in them
    labels = None if info is None else info.output_labels(test.obs_dim, units=scale is None)
    return BenchmarkScore(*metrics, y_sim, x_sim, start, status, n_init, labels)


def _check_record(test: Trajectories, n_init) -> int:
    """``n_init`` in [1, T − 1], something to score in every trajectory, finite data; or raise."""
    T = test.num_steps
    if isinstance(n_init, bool) or not isinstance(n_init, (int, np.integer)):
        raise TypeError(f"`n_init` must be an integer; got {n_init!r}.")
    if not 1 <= n_init <= T - 1:
        raise ValueError(f"`n_init` must be in [1, T − 1] = [1, {T - 1}]; got {n_init}.")
    n_init = int(n_init)
    scored = np.asarray(test.mask)[:, n_init:].any(axis=(1, 2))
    if not scored.all():
        raise ValueError(
            f"trajectory {int(np.argmin(scored))} has no observed output from step "
            f"n_init = {n_init} on: nothing to score."
        )
    y, u, mask = np.asarray(test.y), np.asarray(test.u), np.asarray(test.mask)
    if not (np.all(np.isfinite(np.where(mask, y, 0.0))) and np.all(np.isfinite(u))):
        raise ValueError("`test` has a non-finite observed output or input.")
    return n_init


def _check_scale(scale, m: int) -> np.ndarray:
    """The error scale: ones without ``scale``, else a positive scalar or (m,) vector."""
    try:  # a string, a complex value, a ragged list: not a number, refused below
        s = np.ones((m,)) if scale is None else np.asarray(scale, np.float64)
    except (TypeError, ValueError):
        s = np.asarray(np.nan)
    bad = isinstance(scale, bool) or s.ndim > 1 or s.size not in (1, m)
    if bad or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"`scale` must be a positive scalar or ({m},) vector; got {scale!r}.")
    return s


def _given_start(x1, system: AbstractSystem, test: Trajectories, options: dict):
    """The given initial states, checked, with status ``successful`` (no estimation options)."""
    if options:
        raise TypeError(f"options {sorted(options)} estimate x1, which was given.")
    start = jnp.asarray(x1, test.y.dtype)
    if start.shape != (test.batch_size, system.state_dim):
        raise ValueError(
            f"`x1` must have shape (B, n) = {(test.batch_size, system.state_dim)}; "
            f"got {start.shape}."
        )
    if not np.all(np.isfinite(np.asarray(start))):
        raise ValueError("`x1` has a non-finite value.")
    ok = jnp.ones((test.batch_size,), bool)
    return start, select(ok, RESULTS.successful, RESULTS.successful)


def _flag_diverged(start, rmse_overall, status: RESULTS) -> RESULTS:
    """Status ``diverged`` and a warning where x̂₁ is finite but the free run's score is not.

    (A non-finite x̂₁ was already warned about by ``estimate_initial_state``; its status stays
    ``nonfinite``.)
    """
    finite_start = np.all(np.isfinite(np.asarray(start)), axis=-1)
    bad = finite_start & ~np.isfinite(np.asarray(rmse_overall))
    if not bad.any():
        return status
    which = ", ".join(str(b) for b in np.flatnonzero(bad))
    warn(
        f"benchmark_score: the free-run simulation of trajector{'ies' if bad.sum() > 1 else 'y'} "
        f"{which} is not finite — the model diverges (or overflows) from x̂₁ under the test "
        "inputs — so their RMSE, NRMSE and fit % are not finite. Their status is "
        "RESULTS.diverged (BenchmarkScore.status)."
    )
    return select(as_jax(~bad), status, RESULTS.diverged)


_Scores = tuple[Array, Array, Array, Array, Array, Array]


def _flag_constant(
    test: Trajectories, n_init: int, metrics: _Scores, status: RESULTS
) -> tuple[_Scores, RESULTS]:
    """NaN NRMSE and fit % (and a warning, status ``constant_output``) for constant outputs.

    A scored output that takes one value has no spread: NRMSE = RMSE / 0 is not a score (it read
    inf, or ~1e16 where the mean rounds off the value, and fit % −inf).
    """
    y, mask = np.asarray(test.y)[:, n_init:], np.asarray(test.mask)[:, n_init:]
    high = np.where(mask, y, -np.inf).max(axis=1)
    low = np.where(mask, y, np.inf).min(axis=1)
    constant = high == low  # (B, m); every trajectory has a scored entry (_check_record)
    if not constant.any():
        return metrics, status
    rmse, nrmse, fit, overall = (np.asarray(a) for a in metrics[:4])
    nrmse = np.where(constant, np.nan, nrmse)
    fit = np.where(constant, np.nan, fit)
    which = ", ".join(f"record {b} output {j + 1}" for b, j in np.argwhere(constant))
    warn(
        f"benchmark_score: the scored test output is constant ({which}: one value from n_init "
        "on), so NRMSE = RMSE / std(y) and fit % are undefined and returned as NaN; the RMSE "
        "stands. Their status is RESULTS.constant_output (BenchmarkScore.status)."
    )
    row = constant.any(axis=1)
    out = (
        as_jax(rmse),
        as_jax(nrmse),
        as_jax(fit),
        as_jax(overall),
        as_jax(nrmse.mean(axis=1)),
        as_jax(fit.mean(axis=1)),
    )
    return out, select(as_jax(~row), status, RESULTS.constant_output)


# --------------------------------------------------------------------------------------------
# Monitoring a fit
# --------------------------------------------------------------------------------------------


class DynamicsErrorCallback:
    """A fit callback recording ε(θ) (:func:`dynamics_error`) against a reference every epoch.

    ``fit(..., callbacks=[DynamicsErrorCallback(true_system)])`` adds ``"eps"`` to every epoch's
    history record (``result.history_array("eps")``).

    Args:
        true_system: the reference system.
        name: the key of ε in the history records.
        printer: optional ``printer(info, eps)``, called every epoch (e.g. to print progress).
        **kwargs: options of :func:`dynamics_error` (``key``, ``num``, ``mean``, ``std``).
    """

    def __init__(
        self,
        true_system: AbstractContinuousSystem,
        *,
        name: str = "eps",
        printer: Callable[[Any, float], None] | None = None,
        **kwargs,
    ):
        self.true_system = true_system
        self.name = name
        self.printer = printer
        self.kwargs = kwargs

    def error(self, system: AbstractContinuousSystem) -> float:
        """ε(θ) of ``system`` against the reference (e.g. of the initial guess)."""
        return float(dynamics_error(system, self.true_system, **self.kwargs))

    def __call__(self, info) -> dict[str, float]:
        """ε(θ) of ``info.system`` (an epoch's :class:`ceemx.EpochInfo`) as ``{name: ε}``."""
        eps = self.error(info.system)
        if self.printer is not None:
            self.printer(info, eps)
        return {self.name: eps}


class FitTimer:
    """A fit callback recording the wall time at the end of every epoch (``wall`` in the history).

    Call :meth:`start` just before ``fit``; :meth:`per_epoch` returns the epoch durations (the
    first includes JIT compilation).
    """

    def __init__(self):
        self.t0 = time.perf_counter()
        self.stamps: list[float] = []

    def start(self) -> FitTimer:
        """Reset the clock."""
        self.t0 = time.perf_counter()
        self.stamps = []
        return self

    def __call__(self, info) -> dict[str, float]:
        """Record the time; the returned dict is merged into the epoch's history record."""
        now = time.perf_counter()
        self.stamps.append(now)
        return {"wall": now - self.t0}

    def per_epoch(self) -> list[float]:
        """Durations of the epochs so far."""
        t = [self.t0, *self.stamps]
        return [b - a for a, b in zip(t[:-1], t[1:], strict=False)]


def is_monotone(initial_J: float, history: Sequence[dict], rtol: float = 1e-9) -> bool:
    """Whether J never decreased over the epochs (up to ``rtol·|J|`` of float round-off).

    Args:
        initial_J: J before the first epoch (``FitResult.initial_J``).
        history: the epochs' records, each with ``"J"`` (``FitResult.history``).
        rtol: relative round-off allowance.

    Returns:
        ``True`` when no epoch's J is below the previous one's.
    """
    Js = [initial_J] + [h["J"] for h in history]
    pairs = zip(Js[:-1], Js[1:], strict=True)
    return all(b >= a - rtol * max(abs(a), abs(b), 1.0) for a, b in pairs)
