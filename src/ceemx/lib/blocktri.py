"""Symmetric positive-definite block-tridiagonal matrices.

A symmetric block-tridiagonal matrix with ``T`` diagonal blocks of size ``n x n`` is stored by
its diagonal blocks ``A[t, t]`` and its sub-diagonal blocks ``A[t + 1, t]``; the super-diagonal
blocks are the transposes of the latter. Its Cholesky factor ``L`` (with ``A = L L^T``) is block
lower-bidiagonal and is stored the same way.

All routines are pure JAX (jit/vmap-safe), cost ``O(T n^3)`` and never form a dense
``(T n) x (T n)`` matrix, except :func:`to_dense`, which exists for tests and debugging.
``T == 1`` is supported (the sub-diagonal arrays then have shape ``(0, n, n)``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular as lapack_solve_triangular
from jaxtyping import Array, Bool, Float

from ceemx.lib import dense
from ceemx.lib.dense import after

__all__ = [
    "BlockTridiagonal",
    "BlockTridiagonalCholesky",
    "backward_solve",
    "diagonal_inverses",
    "forward_solve",
    "matvec",
    "to_dense",
    "cholesky",
    "is_finite",
    "solve",
    "cho_solve",
    "logdet",
    "selected_inverse",
]


class BlockTridiagonal(eqx.Module):
    """Symmetric block-tridiagonal matrix.

    Attributes:
        diagonal: Diagonal blocks ``A[t, t]``, shape ``(T, n, n)``.
        lower: Sub-diagonal blocks ``A[t + 1, t]``, shape ``(T - 1, n, n)``. The super-diagonal
            blocks are ``lower[t].T``.

    A batch of matrices (one per trajectory) has leaves with leading axes ``(*batch, T, ...)``;
    the functions below take one matrix and are ``vmap``-ed over the batch.
    """

    diagonal: Float[Array, "*batch T n n"]
    lower: Float[Array, "*batch T-1 n n"]


class BlockTridiagonalCholesky(eqx.Module):
    """Block lower-bidiagonal Cholesky factor ``L`` of a :class:`BlockTridiagonal` ``A = L L^T``.

    Attributes:
        diagonal: Lower-triangular diagonal blocks ``L[t, t]``, shape ``(T, n, n)``.
        lower: Sub-diagonal blocks ``L[t + 1, t]``, shape ``(T - 1, n, n)``.

    Batched like :class:`BlockTridiagonal`.
    """

    diagonal: Float[Array, "*batch T n n"]
    lower: Float[Array, "*batch T-1 n n"]


def _mT(x: Array) -> Array:
    return jnp.swapaxes(x, -1, -2)


def _sym(x: Array) -> Array:
    return 0.5 * (x + _mT(x))


def _as_matrix_rhs(b: Array) -> tuple[Array, bool]:
    """Return ``b`` as ``(T, n, k)`` and whether it was a vector right-hand side."""
    if b.ndim == 2:
        return b[..., None], True
    if b.ndim == 3:
        return b, False
    raise ValueError(f"expected a right-hand side of shape (T, n) or (T, n, k), got {b.shape}")


@jax.jit
def matvec(A: BlockTridiagonal, x: Float[Array, "T n *k"]) -> Float[Array, "T n *k"]:
    """Multiply a block-tridiagonal matrix by a (block) vector.

    Args:
        A: The matrix.
        x: Array of shape ``(T, n)`` or ``(T, n, k)``.

    Returns:
        ``A @ x`` with the same shape as ``x``.
    """
    X, squeeze = _as_matrix_rhs(x)
    y = jnp.einsum("tij,tjk->tik", A.diagonal, X)
    # Sub-diagonal contribution: y[t + 1] += A[t + 1, t] x[t].
    sub = jnp.einsum("tij,tjk->tik", A.lower, X[:-1])
    # Super-diagonal contribution: y[t] += A[t + 1, t]^T x[t + 1].
    sup = jnp.einsum("tji,tjk->tik", A.lower, X[1:])
    y = y.at[1:].add(sub).at[:-1].add(sup)
    return y[..., 0] if squeeze else y


@jax.jit
def to_dense(A: BlockTridiagonal | BlockTridiagonalCholesky) -> Float[Array, "Tn Tn"]:
    """Assemble the dense matrix (for tests and debugging only).

    Args:
        A: A symmetric block-tridiagonal matrix, or a block-bidiagonal Cholesky factor (in which
            case the result is the dense lower-triangular factor).

    Returns:
        Dense array of shape ``(T n, T n)``.
    """
    T, n, _ = A.diagonal.shape
    idx = jnp.arange(T)
    blocks = jnp.zeros((T, T, n, n), A.diagonal.dtype)
    blocks = blocks.at[idx, idx].set(A.diagonal)
    blocks = blocks.at[idx[1:], idx[:-1]].set(A.lower)
    if isinstance(A, BlockTridiagonal):
        blocks = blocks.at[idx[:-1], idx[1:]].set(_mT(A.lower))
    return blocks.transpose(0, 2, 1, 3).reshape(T * n, T * n)


def _mm(a: Array, b: Array) -> Array:
    """The product a @ b of the last two axes; for small blocks a broadcast product and sum.

    Inside a scan that is ``vmap``-ped over trajectories XLA:CPU keeps a small batched ``dot`` as
    its own operation per step, while the product-and-sum fuses with its neighbours (the batched
    block Cholesky at T = 25 000, n = 2: ~9× faster).
    """
    if a.shape[-1] <= dense.UNROLL_MAX and a.shape[-2] <= dense.UNROLL_MAX:
        return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)
    return a @ b


def _cholesky(a: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Cholesky factor of one block: elementwise for small blocks, LAPACK for large ones.

    Inside the scans one LAPACK call per step costs more than the arithmetic of a small block,
    and elementwise code has no
    batched LAPACK call that could deadlock (ceemx.lib.dense). NaN where not positive definite,
    either way.
    """
    if a.shape[-1] <= dense.UNROLL_MAX:
        return dense.cholesky(a)
    return jnp.linalg.cholesky(a)


def _trsm(L: Float[Array, "n n"], b: Float[Array, "n k"], trans: bool = False) -> Array:
    """L⁻¹ b (``trans``: L⁻ᵀ b) for a lower-triangular block; elementwise for small blocks."""
    if L.shape[-1] <= dense.UNROLL_MAX:
        return dense.solve_triangular(L, b, trans=trans, rhs_vector=False)
    return lapack_solve_triangular(L, b, lower=True, trans="T" if trans else 0)


@jax.jit
def cholesky(A: BlockTridiagonal) -> BlockTridiagonalCholesky:
    """Block Cholesky factorisation ``A = L L^T`` by a forward scan over time.

    ``L[0, 0] = chol(A[0, 0])``, ``L[t+1, t] = A[t+1, t] L[t, t]^{-T}`` and
    ``L[t+1, t+1] = chol(A[t+1, t+1] - L[t+1, t] L[t+1, t]^T)``; each diagonal block is
    symmetrised before its factorisation. Cost ``O(T n^3)``.

    Args:
        A: Symmetric positive-definite block-tridiagonal matrix.

    Returns:
        The factor. If ``A`` is not positive definite the factor contains NaNs; check with
        :func:`is_finite`.
    """
    L0 = _cholesky(_sym(A.diagonal[0]))

    def step(L_prev, blocks):
        A_diag, A_low = blocks
        # L_low = A_low L_prev^{-T}  <=>  L_prev L_low^T = A_low^T.
        L_low = _mT(_trsm(L_prev, _mT(A_low)))
        L_diag = _cholesky(_sym(A_diag - _mm(L_low, _mT(L_low))))
        return L_diag, (L_diag, L_low)

    _, (diags, lows) = jax.lax.scan(step, L0, (A.diagonal[1:], A.lower))
    return BlockTridiagonalCholesky(diagonal=jnp.concatenate([L0[None], diags], axis=0), lower=lows)


@jax.jit
def is_finite(L: BlockTridiagonalCholesky) -> Bool[Array, ""]:
    """Whether a Cholesky factor is entirely finite (i.e. the factorisation succeeded).

    Args:
        L: The factor returned by :func:`cholesky`.

    Returns:
        Boolean scalar.
    """
    return jnp.all(jnp.isfinite(L.diagonal)) & jnp.all(jnp.isfinite(L.lower))


def diagonal_inverses(L: BlockTridiagonalCholesky) -> Float[Array, "T n n"] | None:
    """``L[t, t]⁻¹`` for every t, by one LAPACK triangular solve (``None`` for small blocks).

    For blocks above ``UNROLL_MAX`` the solves below use them (pass them to every solve with
    the same factor: each call would otherwise compute them again, and two such LAPACK calls
    left independent of each other can deadlock, ``ceemx.lib.dense``); small blocks are solved
    by elementwise code and need none. Computed after the factorisation (it reads it).
    """
    return None if L.diagonal.shape[-1] <= dense.UNROLL_MAX else _inverses(L)


def _inverses(L: BlockTridiagonalCholesky) -> Float[Array, "T n n"]:
    eye = jnp.broadcast_to(jnp.eye(L.diagonal.shape[-1], dtype=L.diagonal.dtype), L.diagonal.shape)
    return lapack_solve_triangular(L.diagonal, eye, lower=True)


def forward_solve(
    L: BlockTridiagonalCholesky, b: Float[Array, "T n *k"], inv: Array | None = None
) -> Float[Array, "T n *k"]:
    """``y = L⁻¹ b``, the forward half of :func:`solve` (``inv``: :func:`diagonal_inverses`).

    With it ``bᵀ A⁻¹ c = (L⁻¹ b)ᵀ (L⁻¹ c)``: a Schur complement Eᵀ A⁻¹ E needs the forward
    half only.
    """
    B, squeeze = _as_matrix_rhs(b)
    if _by_inverses(L, squeeze, inv):
        inv = _inverses(L) if inv is None else inv
        Y = _forward_by_inverses(L, after(B, inv), inv)
    else:
        # XLA reads L.diagonal[0] from before the factorisation's scan: `after` orders it.
        y0 = _trsm(L.diagonal[0], after(B[0], L.diagonal[-1]))

        def fwd(y_prev, inputs):
            L_diag, L_low, b_t = inputs
            y = _trsm(L_diag, b_t - _mm(L_low, y_prev))
            return y, y

        _, ys = jax.lax.scan(fwd, y0, (L.diagonal[1:], L.lower, B[1:]))
        Y = jnp.concatenate([y0[None], ys], axis=0)
    return Y[..., 0] if squeeze else Y


def backward_solve(
    L: BlockTridiagonalCholesky, y: Float[Array, "T n *k"], inv: Array | None = None
) -> Float[Array, "T n *k"]:
    """``x = L⁻ᵀ y``, the backward half of :func:`solve` (``inv``: :func:`diagonal_inverses`)."""
    Y, squeeze = _as_matrix_rhs(y)
    if _by_inverses(L, squeeze, inv):
        inv = _inverses(L) if inv is None else inv
        X = _backward_by_inverses(L, after(Y, inv), inv)
    else:
        xT = _trsm(L.diagonal[-1], Y[-1], trans=True)

        def bwd(x_next, inputs):
            L_diag, L_low, y_t = inputs
            x = _trsm(L_diag, y_t - _mm(_mT(L_low), x_next), trans=True)
            return x, x

        _, xs = jax.lax.scan(bwd, xT, (L.diagonal[:-1], L.lower, Y[:-1]), reverse=True)
        X = jnp.concatenate([xs, xT[None]], axis=0)
    return X[..., 0] if squeeze else X


@jax.jit
def solve(
    L: BlockTridiagonalCholesky, b: Float[Array, "T n *k"], inv: Array | None = None
) -> Float[Array, "T n *k"]:
    """Solve ``A x = b`` given the block Cholesky factor of ``A``.

    A forward scan solves ``L y = b`` and a backward scan solves ``L^T x = y``. Blocks above
    ``UNROLL_MAX`` with several right-hand sides use the inverted diagonal blocks (``inv``,
    :func:`diagonal_inverses`, computed here when not given): every step is then two matrix
    products instead of a product and a LAPACK triangular solve, whose dispatch costs more than
    its arithmetic. A vector right-hand side is solved step by step (``_by_inverses``).

    Args:
        L: Factor returned by :func:`cholesky`.
        b: Right-hand side of shape ``(T, n)`` or ``(T, n, k)`` (``k`` right-hand sides).
        inv: the factor's :func:`diagonal_inverses` (``None``: computed when needed).

    Returns:
        ``x`` with the same shape as ``b``.
    """
    if inv is None and _by_inverses(L, b.ndim == 2, inv):
        inv = diagonal_inverses(L)
    return backward_solve(L, forward_solve(L, b, inv), inv)


def _by_inverses(L: BlockTridiagonalCholesky, vector: bool, inv: Array | None) -> bool:
    """Whether the solves go through the inverted diagonal blocks rather than per-step solves.

    Blocks above ``UNROLL_MAX`` with several right-hand sides, or with the inverses at hand:
    inverting costs n³ a step once, against a LAPACK dispatch per step and right-hand side.
    A vector right-hand side is solved step by step (a LAPACK triangular solve of n² a step):
    inverting first costs about twice as much from n = 32 up, about the same below.
    """
    if L.diagonal.shape[-1] <= dense.UNROLL_MAX:
        return False
    return inv is not None or not vector


def _forward_by_inverses(L: BlockTridiagonalCholesky, B: Array, inv: Array) -> Array:
    """``L⁻¹ B`` as y_t = L_tt⁻¹ (b_t − L_t,t−1 y_{t−1}): matrix products only."""
    y0 = inv[0] @ B[0]

    def fwd(y_prev, inputs):
        inv_t, L_low, b_t = inputs
        y = inv_t @ (b_t - L_low @ y_prev)
        return y, y

    _, ys = jax.lax.scan(fwd, y0, (inv[1:], L.lower, B[1:]))
    return jnp.concatenate([y0[None], ys], axis=0)


def _backward_by_inverses(L: BlockTridiagonalCholesky, Y: Array, inv: Array) -> Array:
    """``L⁻ᵀ Y`` as x_t = L_tt⁻ᵀ (y_t − L_t+1,tᵀ x_{t+1}): matrix products only."""
    xT = _mT(inv[-1]) @ Y[-1]

    def bwd(x_next, inputs):
        inv_t, L_low, y_t = inputs
        x = _mT(inv_t) @ (y_t - _mT(L_low) @ x_next)
        return x, x

    _, xs = jax.lax.scan(bwd, xT, (inv[:-1], L.lower, Y[:-1]), reverse=True)
    return jnp.concatenate([xs, xT[None]], axis=0)


@jax.jit
def cho_solve(A: BlockTridiagonal, b: Float[Array, "T n *k"]) -> Float[Array, "T n *k"]:
    """Solve ``A x = b`` by factorising ``A`` (convenience for ``solve(cholesky(A), b)``).

    Args:
        A: Symmetric positive-definite block-tridiagonal matrix.
        b: Right-hand side of shape ``(T, n)`` or ``(T, n, k)``.

    Returns:
        ``x`` with the same shape as ``b``.
    """
    return solve(cholesky(A), b)


@jax.jit
def logdet(L: BlockTridiagonalCholesky) -> Float[Array, ""]:
    """Log-determinant of ``A = L L^T``.

    Args:
        L: Factor returned by :func:`cholesky`.

    Returns:
        ``log det A = 2 sum_t sum_i log L[t, t][i, i]`` (scalar).
    """
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L.diagonal, axis1=-2, axis2=-1)))


@jax.jit
def selected_inverse(L: BlockTridiagonalCholesky) -> BlockTridiagonal:
    """Diagonal and sub-diagonal blocks of ``A^{-1}`` from the factor ``A = L L^T``.

    With ``S = A^{-1}``, the identity ``S L = L^{-T}`` (block upper triangular with diagonal
    blocks ``L[t, t]^{-T}``) gives, for ``G_t = L[t+1, t] L[t, t]^{-1}``, the backward
    (RTS-like) recursion

        ``S[T-1, T-1] = (L[T-1, T-1] L[T-1, T-1]^T)^{-1}``,
        ``S[t+1, t] = -S[t+1, t+1] G_t``,
        ``S[t, t] = (L[t, t] L[t, t]^T)^{-1} + G_t^T S[t+1, t+1] G_t``.

    Cost ``O(T n^3)``.

    Args:
        L: Factor returned by :func:`cholesky`.

    Returns:
        A :class:`BlockTridiagonal` whose blocks are ``S[t, t]`` and ``S[t+1, t]``.
    """
    n = L.diagonal.shape[-1]
    eye = jnp.eye(n, dtype=L.diagonal.dtype)
    L_inv = jax.vmap(lambda Ld: _trsm(Ld, eye))(L.diagonal)
    local = _sym(_mT(L_inv) @ L_inv)  # (L_tt L_tt^T)^{-1}
    G = L.lower @ L_inv[:-1]

    def step(S_next, inputs):
        local_t, G_t = inputs
        S_low = -_mm(S_next, G_t)
        S_diag = _sym(local_t - _mm(_mT(G_t), S_low))
        return S_diag, (S_diag, S_low)

    S_last = local[-1]
    _, (diags, lows) = jax.lax.scan(step, S_last, (local[:-1], G), reverse=True)
    return BlockTridiagonal(diagonal=jnp.concatenate([diags, S_last[None]], axis=0), lower=lows)


def add_to_diagonal(A: BlockTridiagonal, d: Float[Array, "*batch T n"]) -> BlockTridiagonal:
    """A + diag(d): adds ``d[..., t, i]`` to entry (i, i) of diagonal block t (batches too)."""
    n = A.diagonal.shape[-1]
    i = jnp.arange(n)
    return BlockTridiagonal(A.diagonal.at[..., i, i].add(d), A.lower)
