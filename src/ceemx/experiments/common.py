"""Shared pieces of the experiments: x64, seeded coupled-Lorenz problems, θ perturbation, output."""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ..data import Trajectories, simulate
from ..models.noise import DiagonalGaussian
from ..systems.lorenz import (
    TRUE_PARAMS,
    CoupledLorenz,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

__all__ = [
    "LorenzProblem",
    "enable_x64",
    "fit_timer",
    "is_monotone",
    "lorenz_problem",
    "output_dir",
    "perturb",
    "perturb_lorenz",
    "plt",
    "save_figure",
    "save_json",
    "save_text",
    "true_lorenz",
    "warm_start",
    "with_noise",
]

TRUE_SIGMA, TRUE_RHO, TRUE_BETA = TRUE_PARAMS


def enable_x64() -> None:
    """Turn on float64 (experiments and the CLI do this at start; the library never does)."""
    jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------------------------
# Problems
# --------------------------------------------------------------------------------------------


def true_lorenz(
    K: int,
    *,
    key=None,
    m: int | None = None,
    coupling: bool = True,
    dt: float = 0.04,
    process_noise: float = 0.01,
    obs_noise: float = 0.01,
) -> CoupledLorenz:
    """θ_true of paper §4.1, with C and H drawn from ``key`` (default ``PRNGKey(4)``).

    (σ, ρ, β) = (10, 28, 8/3) per attractor, C standard normal (full row rank, m = 3K − 2 by
    default), H standard normal off the own-attractor blocks with Frobenius norm 5
    (``coupling=False``: H = 0).
    """
    key = jax.random.PRNGKey(4) if key is None else key
    kc, kh = jax.random.split(key)
    C = random_observation_matrix(kc, K, m)
    H = random_coupling(kh, K) if coupling and K > 1 else jnp.zeros((3 * K, 3 * K))
    ones = jnp.ones((K,))
    return CoupledLorenz(
        TRUE_SIGMA * ones,
        TRUE_RHO * ones,
        TRUE_BETA * ones,
        C,
        H=H,
        dt=dt,
        process_noise=process_noise,
        obs_noise=obs_noise,
    )


def with_noise(system: CoupledLorenz, process_noise: float, obs_noise: float) -> CoupledLorenz:
    """The same system with diagonal Gaussian noise of the given scales (the fit's weights)."""
    dtype = system.sigma.dtype
    pn = DiagonalGaussian(jnp.asarray(process_noise, dtype), system.state_dim)
    on = DiagonalGaussian(jnp.asarray(obs_noise, dtype), system.obs_dim)
    return eqx.tree_at(lambda s: (s.process_noise, s.obs_noise), system, (pn, on))


def perturb(key, tree, frac: float = 0.1, where: Callable | None = None):
    """θ·(1 + U(−frac, frac)) elementwise on the floating-point leaves of ``tree``.

    With ``where``, only on the sub-trees ``where(tree)`` returns, e.g.
    ``lambda s: (s.sigma, s.rho, s.beta, s.H)``. Zeros stay zero (the authors' perturbation is
    multiplicative).
    """
    target = tree if where is None else where(tree)
    leaves, treedef = jtu.tree_flatten(target)
    keys = jax.random.split(key, max(len(leaves), 1))
    out = [
        leaf * (1.0 + jax.random.uniform(k, leaf.shape, leaf.dtype, -frac, frac))
        if eqx.is_inexact_array(leaf)
        else leaf
        for k, leaf in zip(keys, leaves, strict=False)
    ]
    new = jtu.tree_unflatten(treedef, out)
    return new if where is None else eqx.tree_at(where, tree, new)


LORENZ_PARAMS = lambda s: (s.sigma, s.rho, s.beta)  # noqa: E731
LORENZ_PARAMS_H = lambda s: (s.sigma, s.rho, s.beta, s.H)  # noqa: E731


def perturb_lorenz(
    key, system: CoupledLorenz, *, coupling: bool = True, frac: float = 0.1
) -> CoupledLorenz:
    """Initial guess θ·(1 + U(−frac, frac)) of (σ, ρ, β) and, with ``coupling``, of H."""
    return perturb(key, system, frac, LORENZ_PARAMS_H if coupling else LORENZ_PARAMS)


class LorenzProblem(eqx.Module):
    """A simulated identification problem: the true system, its states, the data, a start guess."""

    true_system: CoupledLorenz
    states: jax.Array
    data: Trajectories
    x1: jax.Array
    init_system: CoupledLorenz


def lorenz_problem(
    seed: int,
    true_system: CoupledLorenz,
    *,
    B: int,
    T: int = 128,
    sigma_w: float = 0.0,
    sigma_v: float = 0.01,
    coupling: bool = True,
) -> LorenzProblem:
    """Seeded data and initial guess for a coupled-Lorenz system (paper §4.1).

    From ``PRNGKey(seed)``: x₁ ~ N((−6, −6, 24), 2.5²) per attractor, process noise N(0, σ_w²)
    (none when σ_w = 0), observation noise N(0, σ_v²), and the initial guess
    θ·(1 + U(−0.1, 0.1)) (of H too when ``coupling``).
    """
    k_x1, k_sim, k_theta = jax.random.split(jax.random.PRNGKey(seed), 3)
    K = true_system.K
    x1 = initial_states(k_x1, B, K)
    pn = DiagonalGaussian(sigma_w, 3 * K) if sigma_w > 0 else False
    on = DiagonalGaussian(sigma_v, true_system.obs_dim) if sigma_v > 0 else False
    xs, data = simulate(true_system, k_sim, x1, T, process_noise=pn, obs_noise=on)
    init = perturb_lorenz(k_theta, true_system, coupling=coupling)
    return LorenzProblem(true_system, xs, data, x1, init)


def warm_start(
    system: CoupledLorenz, data: Trajectories, *, process_noise: float = 1.0
) -> jax.Array:
    """Start states without knowing the true ones.

    :func:`ceemx.initialize.from_observations` (least squares through the observation map; the
    directions it does not see are left at 0), then one smoothing pass of ``system`` at its current
    θ with the process noise replaced by ``process_noise`` (weak dynamics weights), which fills in
    the unobserved directions from the dynamics. Smoothing with stiff dynamics weights directly
    from the least-squares states often converges to a wrong basin on chaotic systems.
    """
    from ..initialize import from_observations
    from ..smoothing import smooth

    x0 = from_observations(system, data)
    soft = eqx.tree_at(
        lambda s: s.process_noise,
        system,
        DiagonalGaussian(jnp.asarray(process_noise, x0.dtype), system.state_dim),
    )
    return smooth(soft, data, x0).states


# --------------------------------------------------------------------------------------------
# Monitoring
# --------------------------------------------------------------------------------------------


def is_monotone(initial_J: float, history: Sequence[dict], rtol: float = 1e-9) -> bool:
    """Whether J never decreased over the epochs (up to ``rtol·|J|`` of float round-off)."""
    Js = [initial_J] + [h["J"] for h in history]
    pairs = zip(Js[:-1], Js[1:], strict=True)
    return all(b >= a - rtol * max(abs(a), abs(b), 1.0) for a, b in pairs)


class fit_timer:
    """A fit callback recording the wall time at the end of every epoch (``wall`` in the history).

    Call :meth:`start` just before ``fit``; ``per_epoch()`` returns the epoch durations (the first
    includes JIT compilation).
    """

    def __init__(self):
        self.t0 = time.perf_counter()
        self.stamps: list[float] = []

    def start(self) -> fit_timer:
        """Reset the clock."""
        self.t0 = time.perf_counter()
        self.stamps = []
        return self

    def __call__(self, info) -> dict:
        """Record the time; the returned dict is merged into the epoch's history record."""
        now = time.perf_counter()
        self.stamps.append(now)
        return {"wall": now - self.t0}

    def per_epoch(self) -> list[float]:
        """Durations of the epochs so far."""
        t = [self.t0, *self.stamps]
        return [b - a for a, b in zip(t[:-1], t[1:], strict=False)]


# --------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------


def output_dir(out: str | os.PathLike | None, default: str) -> Path:
    """The output folder (created)."""
    path = Path(default if out is None else out)
    path.mkdir(parents=True, exist_ok=True)
    return path


def _jsonable(obj: Any):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray | jax.Array):
        return _jsonable(np.asarray(obj).tolist())
    if isinstance(obj, np.floating | float):
        f = float(obj)
        return f if math.isfinite(f) else str(f)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def save_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (arrays become lists; non-finite floats become strings)."""
    path = Path(path)
    path.write_text(json.dumps(_jsonable(obj), indent=2) + "\n")
    return path


def save_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file (Markdown tables)."""
    path = Path(path)
    path.write_text(text)
    return path


def plt():
    """``matplotlib.pyplot`` with the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as pyplot

    return pyplot


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Save and close a figure."""
    path = Path(path)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt().close(fig)
    return path
