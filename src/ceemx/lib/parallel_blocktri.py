"""Parallel-in-time solve of symmetric positive-definite block-tridiagonal systems.

:func:`ceemx.lib.blocktri.solve` runs two ``lax.scan`` passes over time: depth O(T). Here the
same system ``A x = b`` is solved by two ``jax.lax.associative_scan`` passes of depth O(log T)
(O(T n³) work, several times the sequential arithmetic), for accelerators, where the sequential
scan leaves the device idle.

**The algorithm: variable elimination on a chain, in information form.** ``A x = b`` minimises
the quadratic ``½ xᵀA x − bᵀx``, a sum over the edges (t−1, t) of the chain of

    ``q_t(x_{t−1}, x_t) = ½ [x_{t−1}; x_t]ᵀ [[P_ll, P_lr], [P_lrᵀ, P_rr]] [x_{t−1}; x_t]
    − h_lᵀ x_{t−1} − h_rᵀ x_t``

with ``P_lr = A[t, t−1]ᵀ`` and each node's diagonal block and right-hand side split in halves
between its two edges (``P_ll = ½A[t−1, t−1]``, ``P_rr = ½A[t, t]``, likewise ``h``). Two
dummy edges, t = 0 (before x_0) and t = T (after x_{T−1}), carry the outer halves and no
coupling. An *element* is such a quadratic on the two end nodes of a run of consecutive edges,
its interior nodes minimised out; joining two runs that share a node m minimises over x_m:

    ``M = P1_rr + P2_ll``, ``P_ll = P1_ll − P1_lr M⁻¹ P1_lrᵀ``, ``P_lr = −P1_lr M⁻¹ P2_lr``,
    ``P_rr = P2_rr − P2_lrᵀ M⁻¹ P2_lr``, ``h_l = h1_l − P1_lr M⁻¹ h_m``,
    ``h_r = h2_r − P2_lrᵀ M⁻¹ h_m`` with ``h_m = h1_r + h2_l``,

computed as the Schur complement of M's n pivots in one bordered symmetric matrix (symmetric
Gaussian elimination, a rank-one update per pivot: a smaller program to compile than
``lib.dense``'s unrolled Cholesky and triangular solves in every join).

Minimisation in any grouping gives the same result, so the join is associative. ``M`` is the
Schur complement of A's principal submatrix over the run's interior nodes onto x_m, hence
SPD whenever A is, and no worse conditioned than A (this is Gaussian elimination in another order,
not a transfer-matrix product). The prefix scan over edges 0..t leaves the forward message
(J_f, h_f) of x_t, the suffix scan over edges t+1..T the backward message (J_b, h_b) — the
information-form counterparts of the parallel filter and smoother elements of Särkkä and
García-Fernández (2021) — and ``x_t = (J_f + J_b)⁻¹ (h_f + h_b)``.

No LAPACK call is emitted (docs/known_issues.md): the joins and the final per-step solves
(x_t as the Schur complement of J in ``[[J, h], [−I, 0]]``) are the same elementwise
elimination. A pivot that is not positive (A not positive definite) → NaN in the solution.
Pure JAX, jit/vmap-safe, knows nothing of EM.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ceemx.lib import dense
from ceemx.lib.blocktri import BlockTridiagonal

__all__ = ["parallel_solve"]


class _Element(NamedTuple):
    """A quadratic on the end nodes (l, r) of a run of edges; leading axis: the elements."""

    P_ll: Array  # (..., n, n)
    P_lr: Array  # (..., n, n)
    P_rr: Array  # (..., n, n)
    h_l: Array  # (..., n, k)
    h_r: Array  # (..., n, k)


def _mT(x: Array) -> Array:
    return jnp.swapaxes(x, -1, -2)


def _eliminate(K: Array, count: int) -> Array:
    """Schur complement of the leading ``count`` pivots of matrices K (..., R, C).

    Gaussian elimination without row exchanges, one pivot at a time:
    K ← K[1:, 1:] − K[1:, 0] K[0, 1:] / K[0, 0] (on symmetric positive-definite pivot blocks as
    stable as a Cholesky factorisation; no LAPACK, a few array operations per pivot, so the
    unrolled program stays small). A pivot that is not positive makes the result NaN.
    """
    for _ in range(count):
        piv = K[..., 0, 0]
        piv = jnp.where(piv > 0, piv, jnp.nan)
        K = K[..., 1:, 1:] - (K[..., 1:, :1] / piv[..., None, None]) * K[..., :1, 1:]
    return K


def _join(e1: _Element, e2: _Element) -> _Element:
    """The run of e1's edges followed by e2's (e1's right node is e2's left node), joined.

    Minimising over the shared node m is the Schur complement of M = P1_rr + P2_ll in the
    bordered symmetric matrix with rows (x_m, x_l, x_r, h):
    ``[[M, P1_lrᵀ, P2_lr, h_m], [P1_lr, P1_ll, 0, h1_l], [P2_lrᵀ, 0, P2_rr, h2_r], [·, ·, ·, 0]]``.
    """
    n = e1.P_ll.shape[-1]
    zero = jnp.zeros_like(e1.P_ll)
    h_m = e1.h_r + e2.h_l
    cols = jnp.concatenate([h_m, e1.h_l, e2.h_r], axis=-2)  # (..., 3n, k)
    top = jnp.concatenate(
        [
            jnp.concatenate([e1.P_rr + e2.P_ll, _mT(e1.P_lr), e2.P_lr], axis=-1),
            jnp.concatenate([e1.P_lr, e1.P_ll, zero], axis=-1),
            jnp.concatenate([_mT(e2.P_lr), zero, e2.P_rr], axis=-1),
        ],
        axis=-2,
    )  # (..., 3n, 3n)
    k = cols.shape[-1]
    bottom = jnp.concatenate([_mT(cols), jnp.zeros((*cols.shape[:-2], k, k), cols.dtype)], -1)
    S = _eliminate(jnp.concatenate([jnp.concatenate([top, cols], -1), bottom], -2), n)
    return _Element(
        P_ll=dense.symmetrize(S[..., :n, :n]),
        P_lr=S[..., :n, n : 2 * n],
        P_rr=dense.symmetrize(S[..., n : 2 * n, n : 2 * n]),
        h_l=S[..., :n, 2 * n :],
        h_r=S[..., n : 2 * n, 2 * n :],
    )


@jax.jit
def parallel_solve(A: BlockTridiagonal, b: Float[Array, "T n *k"]) -> Float[Array, "T n *k"]:
    """Solve ``A x = b`` for SPD block-tridiagonal ``A`` by associative scans (depth O(log T)).

    The same solution as ``blocktri.solve(blocktri.cholesky(A), b)`` up to rounding (tests: 1e-8
    relative in float64), computed by two ``jax.lax.associative_scan`` passes instead of two
    sequential scans; see the module notes. Work O(T n³), several times the sequential solve's:
    faster only where the device has idle parallel lanes (not on CPU).

    Args:
        A: One symmetric positive-definite block-tridiagonal matrix (``vmap`` for a batch).
        b: Right-hand side of shape ``(T, n)`` or ``(T, n, k)``.

    Returns:
        ``x`` with the shape and dtype of ``b``; NaN where ``A`` is not positive definite.
    """
    squeeze = b.ndim == 2
    if b.ndim not in (2, 3):
        raise ValueError(f"expected a right-hand side of shape (T, n) or (T, n, k), got {b.shape}")
    B = b[..., None] if squeeze else b
    T, n, _ = A.diagonal.shape
    half = 0.5 * dense.symmetrize(A.diagonal)
    hb = 0.5 * B
    zero = jnp.zeros((1, n, n), half.dtype)
    zero_h = jnp.zeros((1, *B.shape[1:]), B.dtype)
    # edge t (t = 0..T) joins x_{t−1} and x_t; edges 0 and T have a dummy outer node
    edges = _Element(
        P_ll=jnp.concatenate([zero, half], axis=0),
        P_lr=jnp.concatenate([zero, _mT(A.lower), zero], axis=0),
        P_rr=jnp.concatenate([half, zero], axis=0),
        h_l=jnp.concatenate([zero_h, hb], axis=0),
        h_r=jnp.concatenate([hb, zero_h], axis=0),
    )
    head = jax.tree.map(lambda a: a[:T], edges)  # edges 0..T−1
    tail = jax.tree.map(lambda a: a[1:], edges)  # edges 1..T
    fwd = jax.lax.associative_scan(_join, head)  # [t]: edges 0..t, on (dummy, x_t)
    # reverse=True hands fn (later run, earlier run): swap them back
    bwd = jax.lax.associative_scan(lambda a, c: _join(c, a), tail, reverse=True)
    # bwd[t]: edges t+1..T, on (x_t, dummy)
    # x_t = J⁻¹ h: the Schur complement of J in [[J, h], [−I, 0]] (same elimination)
    J = fwd.P_rr + bwd.P_ll
    eye = jnp.broadcast_to(-jnp.eye(n, dtype=J.dtype), J.shape)
    K = jnp.concatenate(
        [
            jnp.concatenate([J, fwd.h_r + bwd.h_l], axis=-1),
            jnp.concatenate([eye, jnp.zeros_like(B)], axis=-1),
        ],
        axis=-2,
    )
    X = _eliminate(K, n)
    return X[..., 0] if squeeze else X
