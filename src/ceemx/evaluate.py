"""Metrics of identified models: ε(θ) (paper Eq. 14), open-loop simulation RMSE, mean (SE).

- :func:`dynamics_error` — the paper's ε(θ) as the authors computed it: the mean squared difference
  of the continuous-time vector fields of two systems at 1024 random states.
- :func:`simulation_rmse` — noise-free open-loop rollouts compared with the observations.
- :func:`mean_se` — mean and standard error over seeds (an :class:`Estimate`).
- Fit callbacks and checks: :class:`DynamicsErrorCallback` (ε(θ) every epoch),
  :class:`FitTimer` (wall time every epoch), :func:`is_monotone` (J never decreased).

Tables, files and figures are in :mod:`ceemx.report`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .data import Trajectories, rollout_one
from .models.system import AbstractContinuousSystem, AbstractSystem, float_dtype

__all__ = [
    "DynamicsErrorCallback",
    "Estimate",
    "FitTimer",
    "SimulationRMSE",
    "dynamics_error",
    "is_monotone",
    "mean_se",
    "simulation_rmse",
]


# --------------------------------------------------------------------------------------------
# ε(θ), Eq. 14
# --------------------------------------------------------------------------------------------


@eqx.filter_jit
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


@eqx.filter_jit
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
    mask = data.mask
    sq = jnp.where(mask, (pred - data.y) ** 2, 0.0)
    count = jnp.sum(mask, axis=(1, 2))
    per = jnp.sqrt(jnp.sum(sq, axis=(1, 2)) / jnp.maximum(count, 1))
    overall = jnp.sqrt(jnp.sum(sq) / jnp.maximum(jnp.sum(count), 1))
    return SimulationRMSE(per, overall, pred)


# --------------------------------------------------------------------------------------------
# Summaries over seeds
# --------------------------------------------------------------------------------------------


class Estimate(NamedTuple):
    """Mean and standard error (sample std, ddof=1, over √n, as the authors' tables) of n values."""

    mean: float
    se: float
    n: int

    def within(self, truth: float, k: float = 2.0) -> bool:
        """Whether |mean − truth| ≤ k·SE (the paper's Table 1 flags means outside 2 SE)."""
        return bool(abs(self.mean - truth) <= k * self.se)


def mean_se(values) -> Estimate:
    """:class:`Estimate` of a 1-D sample (SE = 0 for a single value)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("mean_se of an empty sample")
    se = float(np.std(v, ddof=1) / np.sqrt(v.size)) if v.size > 1 else 0.0
    return Estimate(float(np.mean(v)), se, int(v.size))


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
