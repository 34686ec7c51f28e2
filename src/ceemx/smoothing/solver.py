"""The smoothing step (paper Eq. 10): batched Levenberg–Marquardt on x with a block-tridiagonal solve."""

from __future__ import annotations

import enum
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .. import linalg
from ..data import Trajectories
from ..linalg import BlockTridiagonal
from ..models.system import AbstractSystem
from ..objective import linearize, neg_log_joint_single

__all__ = ["RESULTS", "LMSmoother", "SmootherSolution", "smooth", "check_inputs"]


class RESULTS(enum.IntEnum):
    """Per-trajectory status codes of iterative solvers."""

    successful = 0
    max_steps_reached = 1
    nonfinite = 2
    stalled = 3

    @property
    def message(self) -> str:
        """Human-readable explanation."""
        return {
            0: "converged",
            1: "reached max_steps before converging",
            2: "the objective or its derivatives are not finite at the initial point",
            3: "no step decreases the objective (damping exhausted) before the tolerances were met",
        }[int(self)]


class LMSmoother(eqx.Module):
    """Levenberg–Marquardt smoother for Eq. 10 (Gauss–Newton for Gaussian noise, IRLS otherwise).

    Minimises −J(x, θ) + ρ_x‖x − x_init‖² for each trajectory independently. Each iteration
    linearises the residuals, assembles the block-tridiagonal Gauss–Newton matrix from per-step
    Jacobian blocks, adds Marquardt damping λ·diag, factors it by a block Cholesky over time
    (O(T n³)) and accepts the step when the actual decrease is a positive fraction of the
    predicted one.

    Attributes:
        rho_x: trust-region weight ρ_x ≥ 0 towards the initial states (paper Eq. 10).
        rtol: converged when the decrease of the objective, or the predicted decrease, is at most
            ``rtol·|objective| + atol``.
        atol: absolute tolerance on the objective.
        max_steps: bound on iterations (accepted and rejected) per trajectory.
        damping: initial Marquardt damping λ₀.
        throw: raise (via ``eqx.error_if``) when any trajectory fails; otherwise report statuses.
    """

    rho_x: float = 0.0
    rtol: float = 1e-10
    atol: float = 0.0
    max_steps: int = eqx.field(default=50, static=True)
    damping: float = 1e-3
    throw: bool = eqx.field(default=False, static=True)


class SmootherSolution(eqx.Module):
    """Result of :func:`smooth`.

    Attributes:
        states: (B, T, n) MAP state trajectories (the initial states where a trajectory failed
            with a non-finite objective).
        objective: (B,) −J(x, θ) at ``states`` (without the ρ_x term).
        iterations: (B,) iterations each trajectory took.
        status: (B,) codes from :class:`RESULTS`.
        covariances: (B, T, n, n) marginal covariances of x_t under the Laplace approximation
            (inverse Gauss–Newton matrix of −J), or ``None`` unless requested.
        cross_covariances: (B, T−1, n, n) Cov(x_{t+1}, x_t), or ``None``.
    """

    states: Float[Array, "B T n"]
    objective: Float[Array, " B"]
    iterations: Int[Array, " B"]
    status: Int[Array, " B"]
    covariances: Float[Array, "B T n n"] | None = None
    cross_covariances: Float[Array, "B T-1 n n"] | None = None

    @property
    def converged(self) -> Array:
        """(B,) True where the trajectory converged."""
        return self.status == RESULTS.successful

    def messages(self) -> list[str]:
        """One status message per trajectory (host-side)."""
        return [RESULTS(int(s)).message for s in np.asarray(self.status)]


class _LMState(NamedTuple):
    x: Array
    f: Array
    lin: object
    lam: Array
    nu: Array
    step: Array
    done: Array
    status: Array


def _damped(hess: BlockTridiagonal, lam, extra_diag) -> BlockTridiagonal:
    n = hess.diagonal.shape[-1]
    d = jnp.diagonal(hess.diagonal, axis1=-2, axis2=-1) + extra_diag
    floor = 1e-12 * jnp.maximum(jnp.max(d), 1.0)
    scale = lam * jnp.maximum(d, floor) + extra_diag
    return BlockTridiagonal(hess.diagonal + scale[..., None] * jnp.eye(n, dtype=d.dtype), hess.lower)


def _quad(hess: BlockTridiagonal, v) -> Array:
    return jnp.sum(v * linalg.matvec(hess, v))


def _smooth_one(solver: LMSmoother, system, x0, y, u, mask):
    rho = jnp.asarray(solver.rho_x, x0.dtype)
    ident = lambda s: s  # noqa: E731

    def objective_and_lin(x):
        lin = linearize(ident, system, x, y, u, mask)
        dx = x - x0
        f = lin.value + rho * jnp.sum(dx**2)
        return f, lin._replace(grad_x=lin.grad_x + 2.0 * rho * dx)

    f0, lin0 = objective_and_lin(x0)
    finite0 = jnp.isfinite(f0) & jnp.all(jnp.isfinite(lin0.grad_x)) & jnp.all(
        jnp.isfinite(lin0.hess_x.diagonal)
    )
    dtype = x0.dtype
    state = _LMState(
        x=x0,
        f=f0,
        lin=lin0,
        lam=jnp.asarray(solver.damping, dtype),
        nu=jnp.asarray(2.0, dtype),
        step=jnp.asarray(0),
        done=~finite0,
        status=jnp.where(finite0, RESULTS.max_steps_reached, RESULTS.nonfinite).astype(jnp.int32),
    )
    tol = lambda f: solver.rtol * jnp.abs(f) + solver.atol  # noqa: E731

    def cond(s):
        return (~s.done) & (s.step < solver.max_steps)

    def body(s):
        A = _damped(s.lin.hess_x, s.lam, 2.0 * rho)
        L = linalg.cholesky(A)
        delta = -linalg.solve(L, s.lin.grad_x)
        ok_solve = linalg.is_finite(L) & jnp.all(jnp.isfinite(delta))
        delta = jnp.where(ok_solve, delta, 0.0)
        pred = -(jnp.sum(s.lin.grad_x * delta) + 0.5 * (_quad(s.lin.hess_x, delta) + 2.0 * rho * jnp.sum(delta**2)))
        x_new = s.x + delta
        f_new, lin_new = objective_and_lin(x_new)
        actual = s.f - f_new
        ratio = actual / jnp.where(pred > 0, pred, 1.0)
        accept = ok_solve & jnp.isfinite(f_new) & (pred > 0) & (ratio > 1e-4)
        accept = accept & jnp.all(jnp.isfinite(lin_new.grad_x))
        # Nielsen's damping update.
        lam_acc = s.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
        lam = jnp.where(accept, lam_acc, s.lam * s.nu)
        nu = jnp.where(accept, 2.0, 2.0 * s.nu)
        x = jnp.where(accept, x_new, s.x)
        f = jnp.where(accept, f_new, s.f)
        lin = jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), lin_new, s.lin)
        small_pred = ok_solve & (pred <= tol(s.f))
        small_actual = accept & (actual <= tol(s.f))
        converged = small_pred | small_actual
        stalled = lam > 1e20
        status = jnp.where(converged, RESULTS.successful, jnp.where(stalled, RESULTS.stalled, s.status))
        return _LMState(x, f, lin, lam, nu, s.step + 1, converged | stalled, status.astype(jnp.int32))

    state = jax.lax.while_loop(cond, body, state)
    value = state.lin.value
    return state.x, value, state.step, state.status, state.lin.hess_x


@eqx.filter_jit
def _smooth_batch(solver, system, x_init, data, covariance: bool):
    x, value, steps, status, hess = jax.vmap(_smooth_one, in_axes=(None, None, 0, 0, 0, 0))(
        solver, system, x_init, data.y, data.u, data.mask
    )
    cov = cross = None
    if covariance:
        sel = jax.vmap(lambda h: linalg.selected_inverse(linalg.cholesky(h)))(hess)
        cov, cross = sel.diagonal, sel.lower
    if solver.throw:
        x = eqx.error_if(x, jnp.any(status != RESULTS.successful), "smoothing failed on a trajectory")
    return SmootherSolution(x, value, steps, status, cov, cross)


def check_inputs(system: AbstractSystem, data: Trajectories, x=None, *, name: str = "x_init") -> None:
    """Validate shapes, finiteness, noise parameters and dtype before any compute (host-side)."""
    if not isinstance(data, Trajectories):
        raise TypeError(f"`data` must be a ceemx.Trajectories; got {type(data).__name__}.")
    system.check()
    if data.obs_dim != system.obs_dim:
        raise ValueError(f"`data.y` has m = {data.obs_dim} but the system observes m = {system.obs_dim}.")
    if data.input_dim != system.input_dim:
        raise ValueError(f"`data.u` has p = {data.input_dim} but the system takes p = {system.input_dim} inputs.")
    if x is not None:
        shape = (data.batch_size, data.num_steps, system.state_dim)
        if tuple(x.shape) != shape:
            raise ValueError(f"`{name}` must have shape (B, T, n) = {shape}; got {tuple(x.shape)}.")
        xa = np.asarray(x)
        if not np.all(np.isfinite(xa)):
            b, t, j = (int(i) for i in np.argwhere(~np.isfinite(xa))[0])
            raise ValueError(f"`{name}` has a non-finite value at index [{b}, {t}, {j}].")
        if xa.dtype != np.asarray(data.y).dtype:
            raise ValueError(f"`{name}` has dtype {xa.dtype} but `data.y` has dtype {data.y.dtype}.")
        if xa.dtype == np.float32 or xa.dtype == np.float16:
            warnings.warn(
                f"identifying in {xa.dtype}: CE-EM's second-order solves lose accuracy in single "
                "precision; enable float64 with jax.config.update('jax_enable_x64', True).",
                stacklevel=3,
            )


def smooth(
    system: AbstractSystem,
    data: Trajectories,
    x_init: Float[Array, "B T n"],
    solver: LMSmoother | None = None,
    *,
    covariance: bool = False,
) -> SmootherSolution:
    """MAP state trajectories for every trajectory of ``data`` (the CE-EM smoothing step, Eq. 10).

    Args:
        system: the model with its current parameters θ.
        data: B trajectories of observations (and inputs, mask).
        x_init: (B, T, n) initial state estimates; also the centre of the ρ_x trust region.
        solver: the smoother configuration (default :class:`LMSmoother`).
        covariance: also return the marginal covariances of each x_t (Laplace approximation), from
            the selected inverse of the Gauss–Newton matrix at the solution.

    Returns:
        A :class:`SmootherSolution`; inspect ``status`` for per-trajectory failures (a failed
        trajectory never changes the others' answers).

    Raises:
        ValueError: on mismatched shapes, non-finite ``x_init`` or invalid noise parameters.

    Trajectories are processed with ``vmap``; compiled once per shape and solver configuration.
    """
    solver = LMSmoother() if solver is None else solver
    check_inputs(system, data, x_init)
    return _smooth_batch(solver, system, jnp.asarray(x_init), data, covariance)
