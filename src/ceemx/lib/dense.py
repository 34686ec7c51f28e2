"""Small dense linear algebra shared by the solvers: SPD solves with a failure flag, whitening.

**No batched LAPACK calls for small blocks.** jaxlib 0.10.2's CPU LAPACK kernels fan a batch out
over XLA's intra-op thread pool and block until it is done; two such calls running at once on a
2-core machine can each hold one of the pool's two threads while waiting for the other's
(docs/known_issues.md). Per-time-step blocks (noise covariances, innovation covariances, the
cubature square roots) are therefore factorised here by elementwise JAX code, batched over any
leading axes: :func:`cholesky` (with a positive-semidefinite mode that truncates rounding-level
pivots, a square root for singular covariances), :func:`solve_triangular`, :func:`cho_solve`
and a Jacobi :func:`eigh` — unrolled up to :data:`UNROLL_MAX` rows (on many small blocks about
100× faster than LAPACK's batched eigh), a ``fori_loop`` over columns beyond. Large
single matrices (one call, which jaxlib never fans out) keep LAPACK: :func:`cholesky_solve`.
Where batched LAPACK calls remain (block-tridiagonal factorisations), :func:`after` orders one
after another.

Everything here is pure JAX (jit/vmap-safe) and knows nothing of EM.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float

__all__ = [
    "UNROLL_MAX",
    "after",
    "cho_solve",
    "cholesky",
    "cholesky_solve",
    "eigh",
    "masked_cholesky",
    "solve_triangular",
    "symmetrize",
    "whiten",
    "whitening_matrix",
]

#: blocks up to this size are factorised by unrolled elementwise code, larger by a column loop
UNROLL_MAX = 8


def after(x: Array, *deps) -> Array:
    """``x`` unchanged, but computed after every array in ``deps`` at run time.

    XLA:CPU runs a program's operations concurrently whenever no buffer of one is read or
    written by the other. ``after`` adds −0·|first element of each dependency| to ``x`` (exactly
    ``x``: x + (−0) = x for every float, signed zeros, infinities and NaN included; no gradient
    flows to ``deps``), so the operation producing ``x``'s new buffer reads the dependencies' and
    everything consuming it runs after them. ``lax.optimization_barrier`` does *not* do this: it
    aliases its operands and emits nothing at run time, so it orders nothing. ``x`` must be a
    floating-point array.
    """
    leaves = [d for d in jax.tree_util.tree_leaves(deps) if jnp.size(d) > 0]
    if not leaves:
        return x
    probe = sum(jnp.real(jnp.ravel(d)[0]).astype(x.dtype) for d in leaves)
    zero = jnp.abs(jnp.where(jnp.isfinite(probe), probe, 0.0)) * jnp.asarray(-0.0, x.dtype)
    return x + lax.stop_gradient(zero)


def _stack(rows: list[list[Array]]) -> Array:
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def _pivot_floor(a: Array) -> Array:
    """Rounding level of the pivots of a (semi)definite matrix: 8·d·ε·max|diag|."""
    d = a.shape[-1]
    diag = jnp.abs(jnp.diagonal(a, axis1=-2, axis2=-1))
    return 8 * d * jnp.finfo(a.dtype).eps * jnp.max(diag, axis=-1)


def cholesky(a: Float[Array, "*batch d d"], *, psd: bool = False) -> Float[Array, "*batch d d"]:
    """Lower Cholesky factor L (L Lᵀ = A) of symmetric matrices, batched; no LAPACK.

    A is symmetrised first (½(A + Aᵀ), as ``jnp.linalg.cholesky`` does).

    Args:
        a: (..., d, d) symmetric matrices.
        psd: ``False``: A must be positive definite; a factor whose pivot is not positive is all
            NaN (as LAPACK's). ``True``: A is positive *semi*-definite up to rounding; a pivot at
            or below the rounding level 8·d·ε·max|diag A| is taken as zero and its column of L
            is zero, so L Lᵀ = A up to that level — a square root of singular and
            rounding-level indefinite covariances (the truncated part is bounded by the same
            level, since |A_ij|² ≤ A_ii A_jj).

    Returns:
        (..., d, d) lower-triangular factors.
    """
    d = a.shape[-1]
    a = symmetrize(a)
    floor = _pivot_floor(a) if psd else jnp.zeros(a.shape[:-2], a.dtype)
    if d <= UNROLL_MAX:
        A = [[a[..., i, j] for j in range(d)] for i in range(d)]
        zero = jnp.zeros_like(A[0][0])
        L = [[zero] * d for _ in range(d)]
        good = jnp.ones(a.shape[:-2], bool)
        for k in range(d):
            piv = A[k][k]
            ok = piv > floor
            good = good & ok
            r = jnp.sqrt(jnp.where(ok, piv, 1.0))
            inv = jnp.where(ok, 1.0 / r, 0.0)
            L[k][k] = jnp.where(ok, r, 0.0)
            for i in range(k + 1, d):
                L[i][k] = A[i][k] * inv
            for i in range(k + 1, d):
                for j in range(k + 1, i + 1):
                    A[i][j] = A[i][j] - L[i][k] * L[j][k]
        out = _stack(L)
    else:
        rows = jnp.arange(d)

        def column(k, carry):
            A, L, good = carry
            col = lax.dynamic_index_in_dim(A, k, axis=-1, keepdims=False)
            piv = lax.dynamic_index_in_dim(col, k, axis=-1, keepdims=False)
            ok = piv > floor
            inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, piv, 1.0)), 0.0)
            lcol = jnp.where(rows >= k, col * inv[..., None], 0.0)
            A = A - lcol[..., :, None] * lcol[..., None, :]
            L = jnp.where(rows[None, :] == k, lcol[..., :, None], L)
            return A, L, good & ok

        init = (a, jnp.zeros_like(a), jnp.ones(a.shape[:-2], bool))
        _, out, good = lax.fori_loop(0, d, column, init)
    if psd:
        return out
    return jnp.where(good[..., None, None], out, jnp.nan)


def solve_triangular(
    L: Float[Array, "*batch d d"],
    b: Float[Array, "*batch d *k"],
    *,
    trans: bool = False,
    rhs_vector: bool | None = None,
) -> Float[Array, "*batch d *k"]:
    """Solve L x = b (``trans``: Lᵀ x = b) for lower-triangular L, batched; no LAPACK.

    Args:
        L: (..., d, d) lower-triangular matrices (the upper triangle is not read).
        b: (..., d) vectors or (..., d, k) matrices of right-hand sides, with the same leading
            axes as ``L``.
        trans: solve with Lᵀ (backward substitution).
        rhs_vector: whether ``b`` holds vectors (default: when ``b.ndim == L.ndim − 1``).

    Returns:
        x, shaped like ``b``.
    """
    d = L.shape[-1]
    vector = b.ndim == L.ndim - 1 if rhs_vector is None else rhs_vector
    B = b[..., None] if vector else b
    order = range(d - 1, -1, -1) if trans else range(d)
    if d <= UNROLL_MAX:
        x: list[Array | None] = [None] * d
        for i in order:
            acc = B[..., i, :]
            done = range(i + 1, d) if trans else range(i)
            for j in done:
                coef = L[..., j, i] if trans else L[..., i, j]
                acc = acc - coef[..., None] * x[j]  # type: ignore[operator]
            x[i] = acc / L[..., i, i][..., None]
        X = jnp.stack(x, axis=-2)  # type: ignore[arg-type]
    else:
        U = jnp.swapaxes(L, -1, -2) if trans else L
        rows = jnp.arange(d)

        def row(step, X):
            i = d - 1 - step if trans else step
            u = lax.dynamic_index_in_dim(U, i, axis=-2, keepdims=False)
            known = (rows > i) if trans else (rows < i)
            acc = lax.dynamic_index_in_dim(B, i, axis=-2, keepdims=False)
            acc = acc - jnp.einsum("...j,...jk->...k", jnp.where(known, u, 0.0), X)
            xi = acc / lax.dynamic_index_in_dim(u, i, axis=-1, keepdims=False)[..., None]
            return jnp.where((rows == i)[:, None], xi[..., None, :], X)

        X = lax.fori_loop(0, d, row, jnp.zeros_like(B))
    return X[..., 0] if vector else X


def cho_solve(
    L: Float[Array, "*batch d d"], b: Float[Array, "*batch d *k"]
) -> Float[Array, "*batch d *k"]:
    """Solve L Lᵀ x = b (L lower-triangular), batched; no LAPACK."""
    vector = b.ndim == L.ndim - 1
    y = solve_triangular(L, b, rhs_vector=vector)
    return solve_triangular(L, y, trans=True, rhs_vector=vector)


def symmetrize(a: Float[Array, "... k k"]) -> Float[Array, "... k k"]:
    """½(A + Aᵀ) over the last two axes."""
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


def cholesky_solve(
    a: Float[Array, "k k"], b: Float[Array, " k"]
) -> tuple[Float[Array, " k"], Bool[Array, ""]]:
    """Solve the symmetric positive-definite system A x = b by Cholesky; flag failure.

    A is symmetrised first. ``ok`` is False when the factor is not finite or has a pivot at
    rounding-noise level (A numerically singular or indefinite); ``x`` is then zeros. For one
    large matrix (LAPACK; do not ``vmap`` it over a batch of large matrices next to other batched
    LAPACK work, see the module docs).
    """
    a = symmetrize(a)
    chol = jnp.linalg.cholesky(a)
    k = a.shape[-1]
    pivots = jnp.diagonal(chol)
    floor = k * jnp.finfo(a.dtype).eps * jnp.max(jnp.abs(jnp.diagonal(a)))
    ok = jnp.all(jnp.isfinite(chol)) & jnp.all(pivots**2 > floor)
    x = jax.scipy.linalg.cho_solve((chol, True), b)
    ok = ok & jnp.all(jnp.isfinite(x))
    return jnp.where(ok, x, 0.0), ok


def _rotation(app, aqq, apq):
    """(c, s) of the Jacobi rotation that zeroes the (p, q) entry (c = 1, s = 0 where it is 0)."""
    zero = apq == 0
    tau = (aqq - app) / (2.0 * jnp.where(zero, 1.0, apq))
    t = jnp.where(tau >= 0, 1.0, -1.0) / (jnp.abs(tau) + jnp.sqrt(1.0 + tau * tau))
    t = jnp.where(zero, 0.0, t)
    c = 1.0 / jnp.sqrt(1.0 + t * t)
    return c, t * c, t


def _sweep_unrolled(A: Array, V: Array) -> tuple[Array, Array]:
    """One cyclic Jacobi sweep over every (p, q), on entries as separate arrays (d ≤ UNROLL_MAX)."""
    d = A.shape[-1]
    a = [[A[..., i, j] for j in range(d)] for i in range(d)]
    v = [[V[..., i, j] for j in range(d)] for i in range(d)]
    for p in range(d - 1):
        for q in range(p + 1, d):
            apq = a[p][q]
            c, s, t = _rotation(a[p][p], a[q][q], apq)
            for k in range(d):
                if k not in (p, q):
                    akp, akq = a[k][p], a[k][q]
                    a[k][p] = a[p][k] = c * akp - s * akq
                    a[k][q] = a[q][k] = s * akp + c * akq
            a[p][p], a[q][q] = a[p][p] - t * apq, a[q][q] + t * apq
            a[p][q] = a[q][p] = jnp.zeros_like(apq)
            for k in range(d):
                vkp, vkq = v[k][p], v[k][q]
                v[k][p], v[k][q] = c * vkp - s * vkq, s * vkp + c * vkq
    return _stack(a), _stack(v)


def _sweep_loop(A: Array, V: Array) -> tuple[Array, Array]:
    """One cyclic Jacobi sweep with the (p, q) pairs in a loop (d > UNROLL_MAX)."""
    d = A.shape[-1]
    pairs = jnp.asarray([(p, q) for p in range(d - 1) for q in range(p + 1, d)])
    idx = jnp.arange(d)

    def rotate(i, carry):
        A, V = carry
        p, q = pairs[i, 0], pairs[i, 1]
        take = lambda M, r, c: M[..., r, c]  # noqa: E731
        c, s, _ = _rotation(take(A, p, p), take(A, q, q), take(A, p, q))
        c, s = c[..., None], s[..., None]
        # columns p, q of A J, then rows p, q of Jᵀ (A J); V ← V J
        ap, aq = A[..., :, p], A[..., :, q]
        A = jnp.where(idx == p, (c * ap - s * aq)[..., :, None], A)
        A = jnp.where(idx == q, (s * ap + c * aq)[..., :, None], A)
        rp, rq = A[..., p, :], A[..., q, :]
        A = jnp.where((idx == p)[:, None], (c * rp - s * rq)[..., None, :], A)
        A = jnp.where((idx == q)[:, None], (s * rp + c * rq)[..., None, :], A)
        vp, vq = V[..., :, p], V[..., :, q]
        V = jnp.where(idx == p, (c * vp - s * vq)[..., :, None], V)
        V = jnp.where(idx == q, (s * vp + c * vq)[..., :, None], V)
        return A, V

    return lax.fori_loop(0, pairs.shape[0], rotate, (A, V))


def eigh(
    a: Float[Array, "*batch d d"], *, sweeps: int | None = None
) -> tuple[Float[Array, "*batch d"], Float[Array, "*batch d d"]]:
    """Eigenvalues and eigenvectors of symmetric matrices by cyclic Jacobi rotations; no LAPACK.

    A fixed number of sweeps (default 8 + ⌈log₂ d⌉; convergence is quadratic, so a handful
    reach rounding level for small blocks, and a sweep over a converged matrix changes nothing),
    so reverse-mode differentiation works.

    Returns:
        ``(w, V)`` with A = V diag(w) Vᵀ, V orthogonal; the eigenvalues in no particular order.
    """
    d = a.shape[-1]
    A = symmetrize(a)
    V = jnp.broadcast_to(jnp.eye(d, dtype=a.dtype), a.shape)
    if d == 1:
        return A[..., 0], V
    sweep = _sweep_unrolled if d <= UNROLL_MAX else _sweep_loop
    n = 8 + math.ceil(math.log2(d)) if sweeps is None else sweeps
    A, V = lax.fori_loop(0, n, lambda _, c: sweep(*c), (A, V))
    return jnp.diagonal(A, axis1=-2, axis2=-1), V


def masked_cholesky(chol: Float[Array, "d d"], mask: Bool[Array, " d"]) -> Float[Array, "d d"]:
    """Cholesky factor of Σ = L Lᵀ restricted to the present rows/columns, identity elsewhere.

    With M = diag(mask), Σ' = M Σ M + (I − M) is, after a permutation, block-diagonal with the
    present block Σ_oo and an identity block, so whitening by chol(Σ') gives the exact marginal
    density of the present components while masked components (residual set to zero) add nothing.
    """
    m = mask.astype(chol.dtype)
    cov = chol @ chol.T
    cov = cov * m[:, None] * m[None, :] + jnp.diag(1.0 - m)
    return cholesky(cov)


def whiten(
    chol: Float[Array, "d d"], mask: Bool[Array, " d"], r: Float[Array, " d"]
) -> Float[Array, " d"]:
    """L_o⁻¹ r_o of the present components (zeros where masked), L_o = :func:`masked_cholesky`."""
    return solve_triangular(masked_cholesky(chol, mask), jnp.where(mask, r, 0.0))


def whitening_matrix(chol: Float[Array, "d d"], mask: Bool[Array, " d"]) -> Float[Array, "d d"]:
    """The matrix S with S r = :func:`whiten` (chol, mask, r): L_o⁻¹ with masked rows zeroed."""
    eye = jnp.eye(chol.shape[-1], dtype=chol.dtype)
    s = solve_triangular(masked_cholesky(chol, mask), eye)
    return s * mask[:, None].astype(chol.dtype)
