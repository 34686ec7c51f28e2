"""Joint Gauss–Newton / Levenberg–Marquardt on (x, θ) through the Schur complement (beyond the paper).

The paper minimises J(x, θ) by alternating blocks (Algorithm 1). Alternation is slow when x and θ
are strongly coupled; a joint second-order step uses that coupling. Its normal equations are an
arrowhead: per trajectory b a block-tridiagonal A_b = J_xᵀWJ_x, a shared dense D = Σ_b J_θᵀWJ_θ,
and the border E_b = J_xᵀWJ_θ. :func:`ceemx.linalg.arrowhead_solve` eliminates x through the Schur
complement S = D − Σ_b E_bᵀA_b⁻¹E_b (p × p) in O(B T (n³ + n² p) + p³) — or matrix-free CG on S
for p > ``dense_max_p`` — and recovers the x-step by block back-substitution.

Each iteration is one accepted Levenberg–Marquardt step with Marquardt's per-variable damping
(scale invariance across parameters of different magnitudes), accepted on actual vs predicted
decrease. ρ_x and ρ_θ are proximal terms centred at the current iterate (they add 2ρ to the
curvature of their block, as in Eq. 10–11); the log-prior is part of the objective.
"""

from __future__ import annotations

import sys
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import checkpoint as ckpt
from . import linalg
from ._lm import RESULTS, levenberg_marquardt, marquardt_scale
from .learning.step import make_problem
from .linalg import BlockTridiagonal
from .objective import linearize

__all__ = ["JointLM", "joint_fit"]


class JointLM(eqx.Module):
    """Options of the joint method (``fit(..., method="joint", joint=JointLM(...))``).

    Attributes:
        rho_x: proximal weight on the states (adds 2ρ_x to their curvature every iteration).
        damping: initial Marquardt λ.
        max_trials: bound on rejected trials within one iteration.
        linear_solver: ``"auto"`` (dense Schur complement when p ≤ ``dense_max_p``, otherwise
            matrix-free preconditioned CG on S), ``"dense"`` or ``"cg"``.
        dense_max_p: threshold of ``"auto"``.
        cg_rtol: relative residual tolerance of CG.
        cg_max_steps: CG iteration bound (``None``: p).
    """

    rho_x: float = 0.0
    damping: float = 1e-3
    max_trials: int = eqx.field(default=30, static=True)
    linear_solver: str = eqx.field(default="auto", static=True)
    dense_max_p: int = eqx.field(default=5000, static=True)
    cg_rtol: float = 1e-12
    cg_max_steps: int | None = eqx.field(default=None, static=True)


def _mask_tree(ok, tree):
    return jax.tree_util.tree_map(
        lambda a: jnp.where(ok.reshape(ok.shape + (1,) * (a.ndim - 1)), a, jnp.zeros_like(a)), tree
    )


def _joint_evaluate(problem, states):
    """``evaluate(z)`` for the LM driver: −J summed over participating trajectories (+ −log prior),
    and the arrowhead's pieces (g_x, g_θ, A, E, D).
    """
    data = problem.data
    ok_b = problem.weights > 0  # trajectories taking part
    eye_n = jnp.eye(states.shape[-1], dtype=states.dtype)
    # Values are −J less its x-independent constants, the scale of the relative tolerances.
    offset = problem.offset(problem.theta_ref)

    def evaluate(z):
        x, th = z
        lin = jax.vmap(
            lambda xb, y, u, m: linearize(problem.build, th, xb, y, u, m, wrt_theta=True)
        )(x, data.y, data.u, data.mask)
        lin = lin._replace(
            value=jnp.where(ok_b, lin.value, 0.0),
            grad_x=_mask_tree(ok_b, lin.grad_x),
            grad_theta=_mask_tree(ok_b, lin.grad_theta),
            E=_mask_tree(ok_b, lin.E),
            D=_mask_tree(ok_b, lin.D),
            # Excluded trajectories get an identity x-block (their states stay put).
            hess_x=BlockTridiagonal(
                jnp.where(ok_b[:, None, None, None], lin.hess_x.diagonal, eye_n),
                _mask_tree(ok_b, lin.hess_x.lower),
            ),
        )
        value = jnp.sum(lin.value) - offset
        g_th = jnp.sum(lin.grad_theta, axis=0)
        D = jnp.sum(lin.D, axis=0)
        if problem.log_prior is not None:
            neg_lp = lambda t: -problem.log_prior(problem.build(t))  # noqa: E731
            value = value + neg_lp(th)
            g_th = g_th + jax.grad(neg_lp)(th)
            h = jax.hessian(neg_lp)(th)
            D = D + 0.5 * (h + h.T)
        return value, (lin.grad_x, g_th, lin.hess_x, lin.E, D)

    return evaluate


@eqx.filter_jit
def _joint_linearize(problem, theta, states):
    """(value, linearisation) at (x, θ): seeds the first iteration; later ones reuse the last."""
    return _joint_evaluate(problem, states)((states, theta))


@eqx.filter_jit
def _joint_iteration(opts: JointLM, problem, theta, states, lam, rtol, current):
    """One accepted LM step on (x, θ) from the linearisation ``current`` = (value, lin) at (x, θ).

    Returns (θ, x, λ, status, accepted, trials, (value, lin) at the new point).
    """
    ok_b = problem.weights > 0
    rho_x = jnp.asarray(opts.rho_x, states.dtype)
    rho_t = problem.rho_theta
    evaluate = _joint_evaluate(problem, states)

    def grad_of(lin):
        return (lin[0], lin[1])

    def solve(lin, lam):
        g_x, g_th, A, E, D = lin
        dA = jnp.diagonal(A.diagonal, axis1=-2, axis2=-1)
        dD = jnp.diagonal(D)
        A_d = linalg.add_to_diagonal(A, marquardt_scale(dA, lam) + 2.0 * rho_x)
        D_d = D + jnp.diag(marquardt_scale(dD, lam) + 2.0 * rho_t)
        sol = linalg.arrowhead_solve(
            A_d,
            E,
            D_d,
            -g_x,
            -g_th,
            method=opts.linear_solver,
            dense_max_p=opts.dense_max_p,
            cg_rtol=opts.cg_rtol,
            cg_max_steps=opts.cg_max_steps,
        )
        dx = jnp.where(ok_b[:, None, None], sol.dx, 0.0)
        return (dx, sol.dtheta), sol.ok

    def quad(lin, delta):
        _, _, A, E, D = lin
        dx, dth = delta
        xAx = jnp.sum(dx * jax.vmap(linalg.matvec)(A, dx))
        xEt = jnp.einsum("btn,btnp,p->", dx, E, dth)
        return (
            xAx
            + 2.0 * xEt
            + dth @ D @ dth
            + 2.0 * rho_x * jnp.sum(dx**2)
            + 2.0 * rho_t * jnp.sum(dth**2)
        )

    out = levenberg_marquardt(
        evaluate,
        grad_of,
        solve,
        quad,
        (states, theta),
        rtol=rtol,
        atol=0.0,
        max_steps=opts.max_trials,
        damping=lam,
        max_accepted=1,
        init=current,
    )
    x, th = out.z
    return th, x, out.damping, out.status, out.accepted, out.steps, (out.value, out.lin)


def joint_fit(
    system,
    data,
    states,
    opts: JointLM,
    *,
    trainable,
    rho_theta,
    log_prior,
    max_iterations,
    tol,
    atol,
    callbacks,
    progress,
    checkpoint,
    initial_J,
):
    """The joint method's outer loop (called by :func:`ceemx.fit`; same history, callbacks, checkpoints)."""
    from .em import EpochInfo, FitResult, _close_epoch, _Progress, _total_J, epoch_record

    B = data.batch_size
    history: list[dict] = []
    problem, theta = make_problem(
        system, states, data, trainable=trainable, rho_theta=rho_theta, log_prior=log_prior
    )
    lam = jnp.asarray(opts.damping, states.dtype)
    status = jnp.zeros((B,), jnp.int32)
    if checkpoint is not None:
        loaded = ckpt.load(checkpoint, (theta, states, lam, status))
        if loaded is not None:
            (theta, states, lam, status), history = loaded
            system = problem.build(theta)
    # Trajectories whose objective is not finite at the start take no part (reported as such).
    _, J_traj = _total_J(system, states, data, np.ones(B))
    weights = np.isfinite(J_traj).astype(float)
    if not weights.all():
        warnings.warn(
            f"trajectories {np.flatnonzero(weights == 0).tolist()} have a non-finite objective at "
            "the initial states; they are excluded from the joint fit.",
            stacklevel=3,
        )
    failed_status = jnp.asarray(np.where(weights > 0, 0, int(RESULTS.nonfinite)), jnp.int32)
    show = sys.stderr.isatty() if progress is None else progress
    bar = _Progress(show, max_iterations, len(history))
    converged = bool(history and history[-1].get("converged", False))
    stopped = bool(history and history[-1].get("stop", False))
    current = None  # (value, linearisation) at the current (x, θ), carried between iterations
    try:
        while len(history) < max_iterations and not (converged or stopped):
            it = len(history) + 1
            problem, theta = make_problem(
                system,
                states,
                data,
                trainable=trainable,
                rho_theta=rho_theta,
                log_prior=log_prior,
                weights=weights,
            )
            t0 = time.perf_counter()
            if current is None:
                current = _joint_linearize(problem, theta, states)
            offset = float(problem.offset(theta))
            value0 = current[0] + offset
            th, x, lam, code, n_acc, trials, current = _joint_iteration(
                opts, problem, theta, states, lam, jnp.asarray(tol, states.dtype), current
            )
            value = current[0] + offset
            th.block_until_ready()
            dt = time.perf_counter() - t0
            code, accepted = int(code), int(n_acc) > 0
            new_system = problem.build(th)
            J_before = -float(value0)
            J_after = -float(value)
            _, J_traj = _total_J(new_system, x, data, weights)
            record = epoch_record(
                it, J_before, J_after, J_traj, th - theta, jnp.linalg.norm(x - states), 0.0, dt,
                trials, code, 0, weights == 0, damping=float(lam),
            )  # fmt: skip
            system, states = new_system, x
            if accepted:
                # Converged when J stops improving (the same rule as Algorithm 1) or the model
                # predicts no further decrease.
                converged = code == RESULTS.successful or bool(
                    J_after - J_before <= tol * abs(J_after + offset) + atol
                )
                run_status = RESULTS.successful
            else:
                converged = code == RESULTS.successful  # predicted decrease below tolerance
                run_status = code
            status = jnp.where(failed_status > 0, failed_status, jnp.int32(run_status))
            stopped = _close_epoch(
                history, record, EpochInfo(it, system, states, record), callbacks, bar, checkpoint,
                (th, states, lam, status), converged,
                halt=not accepted and not converged,  # non-finite, or damping exhausted
            )  # fmt: skip
    finally:
        bar.close()
    return FitResult(system, states, status, history, converged, "joint", initial_J)
