"""Evaluation of identified models: ε(θ) (paper Eq. 14), open-loop simulation RMSE, summary tables.

- :func:`dynamics_error` — the paper's ε(θ) as the authors computed it: the mean squared difference
  of the continuous-time vector fields of two systems at 1024 random states.
- :func:`simulation_rmse` — noise-free open-loop rollouts compared with the observations.
- :func:`mean_se`, :func:`format_estimate`, :func:`parameter_table`, :func:`markdown_table` —
  mean (standard error) summaries over seeds, flagged like the paper's Table 1 when the mean is
  not within two standard errors of the truth.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float

from .data import Trajectories, rollout_one
from .models.system import AbstractContinuousSystem, AbstractSystem

__all__ = [
    "Estimate",
    "SimulationRMSE",
    "default_state_mean",
    "dynamics_error",
    "format_estimate",
    "markdown_table",
    "mean_se",
    "parameter_table",
    "simulation_rmse",
]


# --------------------------------------------------------------------------------------------
# ε(θ), Eq. 14
# --------------------------------------------------------------------------------------------


def _float_dtype(system: AbstractSystem):
    for leaf in jtu.tree_leaves(system):
        if eqx.is_inexact_array(leaf):
            return leaf.dtype
    return jnp.zeros(()).dtype  # pragma: no cover - a system without float parameters


def default_state_mean(system: AbstractSystem) -> Array | None:
    """The paper's initial-state mean for systems that have one, else ``None``.

    For :class:`ceemx.systems.CoupledLorenz` it is (−6, −6, 24) per attractor (paper §4.1).
    """
    from .systems.lorenz import INITIAL_MEAN, CoupledLorenz

    if isinstance(system, CoupledLorenz):
        return jnp.tile(jnp.asarray(INITIAL_MEAN, _float_dtype(system)), system.K)
    return None


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
        mean: (n,) mean of the sampled states; default: the system's paper initial-state mean
            ((−6, −6, 24) per attractor for :class:`~ceemx.systems.CoupledLorenz`); required for
            other systems.
        std: standard deviation of the sampled states (authors: 5).

    Returns:
        A scalar in the systems' dtype.

    Raises:
        ValueError: when ``mean`` is needed but not given, or has the wrong shape.

    Compiled once per system structure and ``num``; safe to call every epoch.

    """
    if mean is None:
        mean = default_state_mean(true_system)
        if mean is None:
            raise ValueError(
                f"`mean` is required for {type(true_system).__name__} "
                "(no default sampling distribution)."
            )
    dtype = _float_dtype(true_system)
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


def format_estimate(
    est: Estimate, truth: float | None = None, *, digits: int = 3, k: float = 2.0
) -> str:
    """``"10.011 (0.012)"``; bold with a ``†`` when ``truth`` is given and is not within k SE."""
    s = f"{est.mean:.{digits}f} ({est.se:.{digits}f})"
    if truth is not None and not est.within(truth, k):
        s = f"**{s}**†"
    return s


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured Markdown table."""
    lines = ["| " + " | ".join(str(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def parameter_table(
    rows: Mapping[str, Mapping[str, tuple[object, float]]],
    *,
    label: str = "setting",
    digits: int = 3,
    k: float = 2.0,
) -> str:
    """Markdown table of mean (SE) per row and parameter, flagging means not within k SE of truth.

    Args:
        rows: row label → {parameter name → (estimates over seeds, true value)}; every row must
            name the same parameters.
        label: header of the first column.
        digits: decimals.
        k: flagging threshold in standard errors (paper: 2).

    Returns:
        The table (a line "† not within k SE of the truth" is appended when any cell is flagged).

    """
    if not rows:
        return ""
    names = list(next(iter(rows.values())).keys())
    body, flagged = [], False
    for name, params in rows.items():
        cells = [name]
        for p in names:
            values, truth = params[p]
            est = mean_se(values)
            flagged |= not est.within(truth, k)
            cells.append(format_estimate(est, truth, digits=digits, k=k))
        body.append(cells)
    truths = ", ".join(f"{p} = {float(next(iter(rows.values()))[p][1]):.{digits}f}" for p in names)
    out = markdown_table([label, *names], body) + f"\nTruth: {truths}.\n"
    if flagged:
        out += f"† mean not within {k:g} standard errors of the truth.\n"
    return out
