"""Starting points of a fit: initial state trajectories and perturbed parameter guesses.

- :func:`from_observations` — states by least squares through the observation map.
- :func:`rollout` — states by simulating the dynamics from guessed initial states.
- :func:`warm_start` — :func:`from_observations`, then a smoothing pass with weak dynamics weights.
- :func:`perturb` — a randomly scaled copy of (part of) a pytree, e.g. a start guess of θ.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, Float, PRNGKeyArray

from ceemx.data.checks import prepare, promote_tree
from ceemx.data.trajectories import Trajectories, rollout_one
from ceemx.inference.smoother import LMSmoother, smooth_prepared
from ceemx.infra.compilation import jit
from ceemx.infra.options import check_callable, check_key, check_nonnegative, check_positive
from ceemx.infra.policy import Runs, entry_point, program
from ceemx.models.system import AbstractSystem, with_noise

__all__ = ["from_observations", "perturb", "rollout", "warm_start", "warm_start_states"]

_T = TypeVar("_T")


@program(runs=Runs.ONCE)
def from_observations(
    system: AbstractSystem, data: Trajectories, x_guess=None, ridge: float = 1e-6
):
    """States by least squares through the observation map linearised at ``x_guess``.

    Per step, x_t = x̄ + argmin_δ ‖S(y_t − g(x̄) − G δ)‖² + ridge·‖δ‖² over the observed
    components, with G = ∂g/∂x at x̄ (``x_guess``, default zeros) and S the observation noise's
    whitening. Unobservable directions stay at x̄ (minimum-norm solution). Use it to start the
    smoother, which then reconciles the states with the dynamics.

    Returns:
        (B, T, n) states.
    """
    B, T, _ = data.y.shape
    n = system.state_dim
    dtype = data.y.dtype
    xbar = jnp.zeros((n,), dtype) if x_guess is None else jnp.asarray(x_guess, dtype)

    def one(y, u, mask, t):
        g0 = system.observe(xbar, u, t)
        G = jax.jacfwd(system.observe)(xbar, u, t)
        S = system.obs_noise.sqrt_curvature(y - g0, mask)
        A = S @ G
        b = S @ jnp.where(mask, y - g0, 0.0)
        lhs = (
            A.T @ A
            + ridge * jnp.trace(A.T @ A) / n * jnp.eye(n, dtype=dtype)
            + 1e-30 * jnp.eye(n, dtype=dtype)
        )
        return xbar + jnp.linalg.solve(lhs, A.T @ b)

    ts = jnp.broadcast_to(jnp.arange(T), (B, T))
    return jax.vmap(jax.vmap(one))(data.y, data.u, data.mask, ts)


@jit
def rollout(system: AbstractSystem, data: Trajectories, x1):
    """States by simulating the noise-free dynamics from guessed initial states ``x1`` (B, n)."""
    return jax.vmap(lambda x0, u: rollout_one(system, x0, u))(jnp.asarray(x1, data.y.dtype), data.u)


@entry_point  # BLAS threads and results as the policy says (ceemx.infra.policy)
def warm_start(
    system: AbstractSystem,
    data: Trajectories,
    *,
    process_noise: float = 1.0,
    smoother: LMSmoother | None = None,
) -> Float[Array, "B T n"]:
    """Start states without knowing the true ones.

    :func:`from_observations` (least squares through the observation map; the directions it does
    not see are left at 0), then one smoothing pass of ``system`` at its current θ with the process
    noise replaced by a diagonal Gaussian of scale ``process_noise`` (weak dynamics weights), which
    fills in the unobserved directions from the dynamics. Smoothing with stiff dynamics weights
    directly from the least-squares states often converges to a wrong basin on chaotic systems.

    Args:
        system: the model at its initial θ.
        data: B observed trajectories.
        process_noise: scale of the process noise during the smoothing pass.
        smoother: the smoothing solver (default :class:`ceemx.LMSmoother`).

    Returns:
        (B, T, n) states.

    Raises:
        TypeError, ValueError: on invalid inputs (as :func:`ceemx.smooth`), before any compute.
    """
    if smoother is not None and not isinstance(smoother, LMSmoother):
        raise TypeError(f"`smoother` must be a ceemx.LMSmoother; got {smoother!r}.")
    check_positive("process_noise", process_noise)
    inputs = prepare(system, data, identify=True)
    return warm_start_states(
        inputs.system, inputs.data, process_noise=process_noise, smoother=smoother
    )


def warm_start_states(
    system: AbstractSystem,
    data: Trajectories,
    *,
    process_noise: float = 1.0,
    smoother: LMSmoother | None = None,
    runs: Runs = Runs.EVERY_EPOCH,
) -> Float[Array, "B T n"]:
    """:func:`warm_start` of prepared inputs (:func:`ceemx.data.checks.prepare`): no checks.

    ``runs``: how often the caller smooths at these shapes — :attr:`~ceemx.infra.policy.Runs.ONCE`
    for a fit whose epochs do not smooth with this program.
    """
    x0 = from_observations(system, data)
    weak = promote_tree(with_noise(system, process_noise=process_noise), system)
    return smooth_prepared(weak, data, x0, smoother, runs=runs).states


def _perturb_leaves(key: PRNGKeyArray, leaves: list, frac: float) -> list:
    """:func:`perturb` of a list of leaves: leaf i by the i-th key split from ``key``."""
    where = tuple(i for i, leaf in enumerate(leaves) if eqx.is_inexact_array(leaf))
    new = _perturbed(key, [leaves[i] for i in where], where, len(leaves), frac)
    out = list(leaves)
    for i, leaf in zip(where, new, strict=True):
        out[i] = leaf
    return out


@program(runs=Runs.ONCE)  # on the host one program per structure (op by op: several per leaf shape)
def _perturbed(key: PRNGKeyArray, arrays: list, where: tuple, count: int, frac: float) -> list:
    keys = jax.random.split(key, max(count, 1))
    return [
        a * (1.0 + jax.random.uniform(keys[i], a.shape, a.dtype, -frac, frac))
        for i, a in zip(where, arrays, strict=True)
    ]


def perturb(
    key: PRNGKeyArray,
    tree: _T,
    frac: float = 0.1,
    where: Callable[[_T], object] | None = None,
) -> _T:
    """θ·(1 + U(−frac, frac)) elementwise on the floating-point array leaves of ``tree``.

    Each leaf gets its own key (split from ``key`` in leaf order). Zeros stay zero (the
    perturbation is multiplicative); integer and non-array leaves are unchanged.

    Args:
        key: PRNG key.
        tree: any pytree, e.g. a system.
        frac: half-width of the relative perturbation.
        where: perturb only the sub-trees ``where(tree)`` returns (as in ``eqx.tree_at``), e.g.
            ``lambda s: (s.sigma, s.rho, s.beta)``; ``None``: every leaf.

    Returns:
        A perturbed copy of ``tree``.
    """
    check_key(key)
    check_nonnegative("frac", frac)
    check_callable("where", where, none=True)
    target = tree if where is None else where(tree)
    leaves, treedef = jtu.tree_flatten(target)
    new = jtu.tree_unflatten(treedef, _perturb_leaves(key, leaves, frac))
    return new if where is None else eqx.tree_at(where, tree, new)
