"""Arrowhead (bordered block-tridiagonal) systems from joint state/parameter Gauss-Newton.

For ``B`` trajectories with states ``x_b`` (``T x n``) and a shared parameter vector of length
``theta``, the Gauss-Newton system is

    ``A_b dx_b + E_b dtheta = r_b``                 for every ``b``,
    ``sum_b E_b^T dx_b + D dtheta = r_theta``,

with ``A_b`` symmetric positive-definite block-tridiagonal. It is solved through the Schur
complement ``S = D - sum_b E_b^T A_b^{-1} E_b``. Every sum over trajectories is a plain
``jnp.sum`` over the leading axis, so sharding that axis later only adds a cross-device reduce.

At very large ``theta`` neither ``S`` (``theta²``) nor the border ``E_b`` (``B·T·n·theta``) can be
held: :func:`arrowhead_solve_matrix_free` takes the border as products instead (``E v``, ``D v`` and
``Eᵀ w``, e.g. Jacobian-vector products of the residuals) and applies ``S`` by CG, each step one
border product, one batched block-tridiagonal solve and one transposed border product.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ceemx.lib.blocktri import (
    BlockTridiagonal,
    BlockTridiagonalCholesky,
    cholesky,
    diagonal_inverses,
    forward_solve,
    is_finite,
    solve,
)
from ceemx.lib.dense import after, cholesky_solve

__all__ = [
    "ArrowheadSolution",
    "arrowhead_solve",
    "arrowhead_solve_matrix_free",
    "factor",
    "pcg",
    "schur_terms",
]


class ArrowheadSolution(eqx.Module):
    """Solution of an arrowhead system.

    Attributes:
        dx: State update, shape ``(B, T, n)``.
        dtheta: Parameter update, shape ``(theta,)``.
        ok: Boolean scalar: every ``A_b`` factor is finite and ``S`` is (numerically) positive
            definite (dense: its Cholesky factor is finite with non-negligible pivots; CG: no
            non-positive curvature was met). When False, ``dx`` and ``dtheta`` are zeros.
        converged: Boolean scalar. Dense: equal to ``ok``. CG: ``ok`` and the relative residual
            reached ``cg_rtol`` within ``cg_max_steps`` (an unconverged CG step with ``ok`` True
            is still a descent direction for a Gauss-Newton step).
        cg_steps: Number of CG iterations taken (0 for the dense method).
        method: ``"dense"``, ``"cg"`` or ``"cg-matrix-free"`` (static).
    """

    dx: Float[Array, "B T n"]
    dtheta: Float[Array, " theta"]
    ok: Bool[Array, ""]
    converged: Bool[Array, ""]
    cg_steps: Int[Array, ""]
    method: str = eqx.field(static=True)


def _solve_b(L: BlockTridiagonalCholesky, b: Array, inv: Array | None = None) -> Array:
    """Batched ``A_b^{-1} b_b`` over the leading trajectory axis (``inv``: see :func:`factor`)."""
    return jax.vmap(solve)(L, b, inv)


def factor(A: BlockTridiagonal) -> tuple[BlockTridiagonalCholesky, Array | None]:
    """The batched block Cholesky factors of ``A_b`` and their diagonal blocks' inverses.

    The inverses (:func:`~ceemx.lib.blocktri.diagonal_inverses`, ``None`` for small blocks) are
    computed once, by one LAPACK call after the factorisation, and passed to every solve with
    these factors: the solves are then matrix products only.
    """
    L = jax.vmap(cholesky)(A)
    return L, jax.vmap(diagonal_inverses)(L)


def schur_terms(
    L: BlockTridiagonalCholesky, inv: Array | None, E: Array, r: Array | None = None
) -> tuple[Array, Array | None]:
    """``(Σ_b E_bᵀ A_b⁻¹ E_b, Σ_b E_bᵀ A_b⁻¹ r_b)`` by forward substitution alone.

    With W_b = L_b⁻¹ E_b and w_b = L_b⁻¹ r_b (one forward pass over [r_b | E_b]) the two are
    Σ W_bᵀ W_b and Σ W_bᵀ w_b: half the triangular work of A_b⁻¹ E_b. ``r`` may be ``None``.
    """
    rhs = E if r is None else jnp.concatenate([r[..., None], E], axis=-1)
    Wf = jax.vmap(forward_solve)(L, rhs, inv)
    W = Wf if r is None else Wf[..., 1:]
    EtE = jnp.einsum("btnp,btnq->pq", W, W)  # one product over (b, t, n), not B summed
    Etr = None if r is None else jnp.einsum("btnp,btn->p", W, Wf[..., 0])
    return EtE, Etr


def _schur_diag(L, E, chunk: int, inv: Array | None = None):
    """Exact ``diag(sum_b E_b^T A_b^{-1} E_b)``, computed over column chunks of ``E``.

    Peak memory is ``O(B T n chunk)`` instead of ``O(B T n theta)``.
    """
    P = E.shape[-1]
    chunk = max(1, min(chunk, P))
    n_chunks = -(-P // chunk)
    pad = n_chunks * chunk - P
    Ep = jnp.pad(E, [(0, 0)] * 3 + [(0, pad)])
    Ec = jnp.moveaxis(Ep.reshape(*E.shape[:3], n_chunks, chunk), 3, 0)

    def one(Ei):
        return jnp.sum(Ei * _solve_b(L, Ei, inv), axis=(0, 1, 2))

    return jax.lax.map(one, Ec).reshape(-1)[:P]


def pcg(S_mv, rhs, m_inv, rtol, max_steps):
    """Bounded preconditioned CG on ``S x = rhs`` that flags non-positive curvature.

    Args:
        S_mv: ``v -> S v`` for a symmetric ``S`` (a vector of ``rhs``'s shape).
        rhs: the right-hand side.
        m_inv: the inverse of a diagonal preconditioner (same shape as ``rhs``).
        rtol: stop at ``||r|| <= rtol ||rhs||``.
        max_steps: bound on iterations (may be traced).

    Returns:
        ``(x, steps, converged, broken)``; ``broken`` when a direction of non-positive (or
        non-finite) curvature was met (``x`` is then the iterate before it).
    """
    b_norm = jnp.linalg.norm(rhs)
    tol = rtol * b_norm
    x0 = jnp.zeros_like(rhs)
    z0 = m_inv * rhs
    state0 = (x0, rhs, z0, jnp.vdot(rhs, z0), jnp.asarray(0, jnp.int32), jnp.asarray(False))

    def cond(state):
        _, r, _, _, k, broken = state
        return (k < max_steps) & (jnp.linalg.norm(r) > tol) & ~broken

    def body(state):
        x, r, d, rz, k, _ = state
        Sd = S_mv(d)
        dSd = jnp.vdot(d, Sd)
        broken = ~(dSd > 0) | ~jnp.isfinite(dSd)
        alpha = jnp.where(broken, 0.0, rz / jnp.where(broken, 1.0, dSd))
        x = x + alpha * d
        r = r - alpha * Sd
        z = m_inv * r
        rz_new = jnp.vdot(r, z)
        beta = rz_new / jnp.where(rz == 0, 1.0, rz)
        return x, r, z + beta * d, rz_new, k + 1, broken

    x, r, _, _, k, broken = jax.lax.while_loop(cond, body, state0)
    converged = jnp.linalg.norm(r) <= tol
    return x, k, converged, broken


@functools.partial(
    jax.jit,
    static_argnames=("method", "cg_max_steps", "dense_max_p", "cg_preconditioner", "cg_chunk"),
)
def arrowhead_solve(
    A: BlockTridiagonal,
    E: Float[Array, "B T n theta"],
    D: Float[Array, "theta theta"],
    r_x: Float[Array, "B T n"],
    r_theta: Float[Array, " theta"],
    *,
    method: Literal["auto", "dense", "cg"] = "auto",
    cg_rtol: float | Float[Array, ""] = 1e-10,
    cg_max_steps: int | None = None,
    dense_max_p: int = 5000,
    cg_preconditioner: Literal["schur_diag", "d_diag", "none"] = "schur_diag",
    cg_chunk: int = 64,
) -> ArrowheadSolution:
    """Solve the arrowhead system by the Schur complement on the parameter block.

    Factors every ``A_b`` (vmapped :func:`~ceemx.lib.blocktri.cholesky`), computes
    ``rhs = r_theta - sum_b E_b^T A_b^{-1} r_b``, solves ``S dtheta = rhs`` with
    ``S = D - sum_b E_b^T A_b^{-1} E_b``, then ``dx_b = A_b^{-1} (r_b - E_b dtheta)``.

    Methods:
        * ``"dense"``: forms ``Z_b = A_b^{-1} E_b`` and ``S`` (``P x P``, ``P`` the length of
          ``theta``) and factors ``S`` by Cholesky. Cost ``O(B T (n^3 + n^2 P) + B T n P^2 +
          P^3)``, memory ``O(B T n P + P^2)``.
        * ``"cg"``: matrix-free preconditioned CG on ``S`` (``S`` and ``Z`` are never formed);
          each step costs one batched block-tridiagonal solve, ``S v = D v - sum_b E_b^T
          A_b^{-1} (E_b v)``. The loop is a ``lax.while_loop`` bounded by ``cg_max_steps``
          (default ``P``) and stops at ``||r|| <= cg_rtol ||rhs||``. Jacobi preconditioner:
          ``"schur_diag"`` (default) uses the exact ``diag(S)``, obtained from ``ceil(P /
          cg_chunk)`` multi-RHS solves with ``cg_chunk`` columns each (one pass whose cost equals
          forming ``Z`` once, at ``O(B T n cg_chunk)`` memory); ``"d_diag"`` uses ``diag(D)``
          (free, weaker); ``"none"`` disables preconditioning. Non-positive diagonal entries
          fall back to 1.
        * ``"auto"``: ``"dense"`` if ``P <= dense_max_p`` else ``"cg"``, decided statically from
          ``D.shape``.

    Args:
        A: Batched block-tridiagonal matrices (every leaf has leading axis ``B``).
        E: Coupling blocks, shape ``(B, T, n, theta)``.
        D: Symmetric parameter block, shape ``(theta, theta)``.
        r_x: State right-hand sides, shape ``(B, T, n)``.
        r_theta: Parameter right-hand side, shape ``(theta,)``.
        method: ``"auto"``, ``"dense"`` or ``"cg"``.
        cg_rtol: Relative residual tolerance of CG.
        cg_max_steps: Maximum CG iterations (default ``P``).
        dense_max_p: Largest ``P`` for which ``"auto"`` picks the dense method.
        cg_preconditioner: ``"schur_diag"``, ``"d_diag"`` or ``"none"`` (see above).
        cg_chunk: Column chunk size for the ``"schur_diag"`` preconditioner.

    Returns:
        An :class:`ArrowheadSolution`. ``ok`` is False (and ``dx``, ``dtheta`` are zeros) when any
        ``A_b`` factor is non-finite or ``S`` is not positive definite.
    """
    P = D.shape[-1]
    if method == "auto":
        method = "dense" if P <= dense_max_p else "cg"
    if method not in ("dense", "cg"):
        raise ValueError(f"unknown method {method!r}")

    L, inv = factor(A)
    a_ok = jnp.all(jax.vmap(is_finite)(L))
    if method == "dense":
        dx, dtheta, s_ok, steps, converged = _dense_schur(L, inv, E, D, r_x, r_theta)
    else:
        cg = (_cg_preconditioner(cg_preconditioner), cg_rtol, cg_max_steps, cg_chunk)
        dx, dtheta, s_ok, steps, converged = _cg_schur(L, inv, E, D, r_x, r_theta, *cg)
    ok = a_ok & s_ok & jnp.all(jnp.isfinite(dx)) & jnp.all(jnp.isfinite(dtheta))
    dx = jnp.where(ok, dx, 0.0).astype(r_x.dtype)
    dtheta = jnp.where(ok, dtheta, 0.0).astype(r_theta.dtype)
    return ArrowheadSolution(dx, dtheta, ok, ok & converged, steps, method)


# Batched block solves with the same factors are never left independent of each other (two
# batched LAPACK calls running at once can deadlock, ceemx.lib.dense): the solves read the
# inverses of the factors' diagonal blocks, computed once (no LAPACK call in the solves then);
# the dense method's final solve needs dθ, the CG method orders its solves after A_b⁻¹ r_b.


def _dense_schur(L, inv, E, D, r_x, r_theta):
    """(dx, dθ, S positive definite, 0 steps, converged): S formed and factored."""
    EtZ, Etw = schur_terms(L, inv, E, r_x)
    assert Etw is not None
    dtheta, s_ok = cholesky_solve(D - EtZ, r_theta - Etw)
    steps = jnp.asarray(0, jnp.int32)
    converged = jnp.asarray(True)
    dx = _solve_b(L, r_x - jnp.einsum("btnp,p->btn", E, dtheta), inv)
    return dx, dtheta, s_ok, steps, converged


def _cg_preconditioner(name: str) -> str:
    """The CG preconditioner's name, checked."""
    if name not in ("schur_diag", "d_diag", "none"):
        raise ValueError(f"unknown cg_preconditioner {name!r}")
    return name


def _cg_schur(L, inv, E, D, r_x, r_theta, preconditioner, cg_rtol, cg_max_steps, cg_chunk):
    """(dx, dθ, no breakdown and finite, CG steps, converged): S v applied, never formed."""
    P = D.shape[-1]
    w = _solve_b(L, r_x, inv)
    E = after(E, w)
    rhs = r_theta - jnp.sum(jnp.einsum("btnp,btn->bp", E, w), axis=0)

    def S_mv(v):
        Ev = jnp.einsum("btnp,p->btn", E, v)
        return D @ v - jnp.sum(jnp.einsum("btnp,btn->bp", E, _solve_b(L, Ev, inv)), axis=0)

    if preconditioner == "schur_diag":
        d = jnp.diagonal(D) - _schur_diag(L, E, cg_chunk, inv)
    elif preconditioner == "d_diag":
        d = jnp.diagonal(D)
    else:
        d = jnp.ones((P,), D.dtype)
    m_inv = jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 1.0)
    max_steps = P if cg_max_steps is None else cg_max_steps
    dtheta, steps, converged, broken = pcg(S_mv, rhs, m_inv, cg_rtol, max_steps)
    s_ok = ~broken & jnp.all(jnp.isfinite(dtheta))
    dx = w - _solve_b(L, jnp.einsum("btnp,p->btn", E, dtheta), inv)
    return dx, dtheta, s_ok, steps, converged


def arrowhead_solve_matrix_free(
    A: BlockTridiagonal,
    border: Callable[[Array], tuple[Array, Array]],
    border_t: Callable[[Array], Array],
    r_x: Float[Array, "B T n"],
    r_theta: Float[Array, " theta"],
    *,
    preconditioner: Float[Array, " theta"] | None = None,
    cg_rtol: float | Float[Array, ""] = 1e-10,
    cg_max_steps: int | Int[Array, ""] | None = None,
) -> ArrowheadSolution:
    """Solve the arrowhead system with the border and ``D`` given as products (matrix-free).

    The same system as :func:`arrowhead_solve`, but neither ``E_b`` (``B·T·n·theta``) nor ``D``
    nor ``S`` is formed: ``S dtheta = rhs`` is solved by preconditioned CG (:func:`pcg`), each
    step costing one ``border`` product, one batched block-tridiagonal solve with the factors of
    ``A_b`` (computed once) and one ``border_t`` product. Memory ``O(B T n² + theta)``.
    Call it inside a compiled function (it takes Python callables).

    Args:
        A: Batched block-tridiagonal matrices (every leaf has leading axis ``B``), SPD.
        border: ``v -> (E v, D v)`` for ``v`` of shape ``(theta,)``: the stacked ``E_b v``
            ``(B, T, n)`` and ``D v`` ``(theta,)`` (one Jacobian-vector product in θ and one
            vector-Jacobian product for Gauss–Newton matrices; damping of ``D`` included).
        border_t: ``w -> sum_b E_b^T w_b`` for ``w`` of shape ``(B, T, n)``.
        r_x: State right-hand sides, shape ``(B, T, n)``.
        r_theta: Parameter right-hand side, shape ``(theta,)``.
        preconditioner: a positive diagonal approximating ``S`` (e.g. the damped ``diag(D)``)
            or ``None`` (no preconditioning). Non-positive entries fall back to 1.
        cg_rtol: relative residual tolerance of CG (a truncated, inexact-Newton step when
            loose: an unconverged CG step is still a descent direction of the model).
        cg_max_steps: bound on CG iterations (default ``theta``).

    Returns:
        An :class:`ArrowheadSolution` with ``method="cg-matrix-free"``; ``ok`` False (and zero
        steps) when an ``A_b`` factor is not finite or CG met non-positive curvature in ``S``.
    """
    P = r_theta.shape[0]
    L, inv = factor(A)
    a_ok = jnp.all(jax.vmap(is_finite)(L))
    w = _solve_b(L, r_x, inv)  # A_b^{-1} r_b
    rhs = r_theta - border_t(w)

    def S_mv(v):
        Ev, Dv = border(v)
        return Dv - border_t(_solve_b(L, Ev, inv))

    if preconditioner is None:
        m_inv = jnp.ones((P,), r_theta.dtype)
    else:
        d = preconditioner
        m_inv = jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 1.0)
    max_steps = P if cg_max_steps is None else cg_max_steps
    dtheta, steps, converged, broken = pcg(S_mv, rhs, m_inv, cg_rtol, max_steps)
    s_ok = ~broken & jnp.all(jnp.isfinite(dtheta))
    Ed, _ = border(dtheta)
    dx = w - _solve_b(L, Ed, inv)
    ok = a_ok & s_ok & jnp.all(jnp.isfinite(dx))
    return ArrowheadSolution(
        dx=jnp.where(ok, dx, 0.0).astype(r_x.dtype),
        dtheta=jnp.where(ok, dtheta, 0.0).astype(r_theta.dtype),
        ok=ok,
        converged=ok & converged,
        cg_steps=steps,
        method="cg-matrix-free",
    )
