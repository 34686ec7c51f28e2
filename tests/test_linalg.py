"""Tests for ceemx.lib (block-tridiagonal and arrowhead solvers) against dense NumPy."""

import pathlib
import sys

import equinox as eqx
import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

try:  # allow running from a checkout without an installed package
    import ceemx  # noqa: F401
except ImportError:  # pragma: no cover
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "src"))

import jax.numpy as jnp  # noqa: E402

from ceemx.lib import (  # noqa: E402
    BlockTridiagonal,
    arrowhead_solve,
    cho_solve,
    cholesky,
    is_finite,
    logdet,
    matvec,
    selected_inverse,
    solve,
    to_dense,
)
from ceemx.lib.arrowhead import factor, schur_terms  # noqa: E402
from ceemx.lib.blocktri import backward_solve, forward_solve  # noqa: E402
from ceemx.lib.tree import as_jax  # noqa: E402

# (1, 1) is the edge of both n = 1 (1×1 blocks) and T = 1 (empty sub-diagonal, zero-length
# scans), (3, 4) the general case of small blocks (elementwise kernels), (9, 3) that of large ones
# (LAPACK factors, solves by the inverted diagonal blocks); (1, 5) and (3, 1) check each edge
# again with the other dimension general (no code path of ceemx.lib.blocktri depends on n = 1 or
# T = 1), so they are slow with the larger shapes. Every test of the family uses these shapes:
# one compilation per shape.
SHAPES = [
    (1, 1),
    (3, 4),
    (9, 3),
    pytest.param(1, 5, marks=pytest.mark.slow),
    pytest.param(3, 1, marks=pytest.mark.slow),
    pytest.param(5, 17, marks=pytest.mark.slow),
    pytest.param(8, 32, marks=pytest.mark.slow),
]


def random_spd(rng, n, T, shift=1.0):
    """Random SPD block-tridiagonal J^T J + shift I with J random block lower-bidiagonal."""
    Jd = rng.standard_normal((T, n, n))
    Jl = rng.standard_normal((T - 1, n, n))
    # A = J^T J: A_tt = Jd_t^T Jd_t + Jl_t^T Jl_t, A_{t+1,t} = Jd_{t+1}^T Jl_t.
    diag = np.einsum("tji,tjk->tik", Jd, Jd) + shift * np.eye(n)
    diag[:-1] += np.einsum("tji,tjk->tik", Jl, Jl)
    lower = np.einsum("tji,tjk->tik", Jd[1:], Jl)
    return BlockTridiagonal(diagonal=as_jax(diag), lower=as_jax(lower))


def dense_np(A):
    """The dense matrix of a block-tridiagonal ``A`` in NumPy (no compilation)."""
    diag, lower = np.asarray(A.diagonal), np.asarray(A.lower)
    T, n = diag.shape[:2]
    K = np.zeros((T, n, T, n))
    for t in range(T):
        K[t, :, t, :] = diag[t]
    for t in range(T - 1):
        K[t + 1, :, t, :] = lower[t]
        K[t, :, t + 1, :] = lower[t].T
    return K.reshape(T * n, T * n)


def rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300)


@jax.jit
def _factor_and_solve(A, x, X, b, Bm):
    """Every block-tridiagonal operation at once: one compilation per shape, shared by the tests
    of this family (eager op-by-op evaluation compiles each operation separately and costs
    seconds)."""
    L = cholesky(A)
    return dict(
        forward_B=forward_solve(L, Bm),
        backward_B=backward_solve(L, Bm),
        dense=to_dense(A),
        Ax=matvec(A, x),
        AX=matvec(A, X),
        finite=is_finite(L),
        L=to_dense(L),
        solve_b=solve(L, b),
        solve_B=solve(L, Bm),
        cho_solve=cho_solve(A, b),
        logdet=logdet(L),
        selected_inverse=selected_inverse(L),
    )


def _everything(rng, A):
    """``_factor_and_solve`` of ``A`` with random right-hand sides (returned first)."""
    T, n = A.diagonal.shape[:2]
    x = rng.standard_normal((T, n))
    X = rng.standard_normal((T, n, 3))
    b = rng.standard_normal((T, n))
    Bm = rng.standard_normal((T, n, 4))
    return (x, X, b, Bm), _factor_and_solve(A, x, X, b, Bm)


@pytest.mark.parametrize("n,T", SHAPES)
def test_dense_matvec_solve_logdet(n, T):
    rng = np.random.default_rng(n * 100 + T)
    A = random_spd(rng, n, T)
    (x, X, b, Bm), out = _everything(rng, A)

    Ad = np.asarray(out["dense"])
    assert Ad.shape == (T * n, T * n)
    np.testing.assert_array_equal(Ad, dense_np(A))
    np.testing.assert_allclose(Ad, Ad.T)
    np.testing.assert_allclose(out["Ax"], (Ad @ x.ravel()).reshape(T, n), rtol=1e-12)
    np.testing.assert_allclose(out["AX"], (Ad @ X.reshape(T * n, 3)).reshape(T, n, 3), rtol=1e-12)

    assert bool(out["finite"])
    Ld = np.asarray(out["L"])
    assert rel_err(Ld @ Ld.T, Ad) < 1e-12
    # The two halves of a solve: L⁻¹ B and L⁻ᵀ B (the Schur complement's forward passes).
    B2 = Bm.reshape(T * n, 4)
    assert rel_err(out["forward_B"], np.linalg.solve(Ld, B2).reshape(T, n, 4)) < 1e-10
    assert rel_err(out["backward_B"], np.linalg.solve(Ld.T, B2).reshape(T, n, 4)) < 1e-10

    assert rel_err(out["solve_b"], np.linalg.solve(Ad, b.ravel()).reshape(T, n)) < 1e-10
    ref = np.linalg.solve(Ad, Bm.reshape(T * n, 4)).reshape(T, n, 4)
    assert rel_err(out["solve_B"], ref) < 1e-10
    assert rel_err(out["cho_solve"], np.linalg.solve(Ad, b.ravel()).reshape(T, n)) < 1e-10

    sign, ld = np.linalg.slogdet(Ad)
    assert sign == 1
    assert abs(float(out["logdet"]) - ld) <= 1e-10 * max(1.0, abs(ld))


@pytest.mark.parametrize("n,T", SHAPES)
def test_selected_inverse(n, T):
    rng = np.random.default_rng(7 + n * 100 + T)
    A = random_spd(rng, n, T)
    _, out = _everything(rng, A)
    inv = np.linalg.inv(dense_np(A)).reshape(T, n, T, n)
    S = out["selected_inverse"]
    assert S.diagonal.shape == (T, n, n) and S.lower.shape == (T - 1, n, n)
    t = np.arange(T)
    assert rel_err(S.diagonal, inv[t, :, t, :]) < 1e-10
    if T > 1:
        assert rel_err(S.lower, inv[t[1:], :, t[:-1], :]) < 1e-10


def test_jit_and_vmap():
    rng = np.random.default_rng(0)
    n, T, batch = 3, 4, 4
    mats = [random_spd(rng, n, T) for _ in range(batch)]
    A = jax.tree.map(lambda *xs: jnp.stack(xs), *mats)
    b = rng.standard_normal((batch, T, n))

    @jax.jit  # one compilation of the three vmapped operations
    @jax.vmap
    def batched(a, b):
        x = cho_solve(a, b)
        return x, logdet(cholesky(a)), matvec(a, x)

    x, ld, Ax = batched(A, b)
    for i, Ai in enumerate(mats):
        Ad = dense_np(Ai)
        assert rel_err(x[i], np.linalg.solve(Ad, b[i].ravel()).reshape(T, n)) < 1e-10
        assert abs(float(ld[i]) - np.linalg.slogdet(Ad)[1]) < 1e-9
    np.testing.assert_allclose(Ax, b, rtol=1e-9, atol=1e-10)


def test_not_pd_is_detected():
    rng = np.random.default_rng(1)
    A = random_spd(rng, 3, 4)  # a shape of SHAPES: the compiled _factor_and_solve
    diag = np.array(A.diagonal)
    diag[2] -= 1e3 * np.eye(3)  # in NumPy: an eager `.at[].add` compiles a program
    bad = BlockTridiagonal(diagonal=jnp.asarray(diag), lower=A.lower)
    assert not bool(_everything(rng, bad)[1]["finite"])
    assert bool(_everything(rng, A)[1]["finite"])


def test_float32_in_float32_out():
    rng = np.random.default_rng(2)
    A64 = random_spd(rng, 3, 4)
    A = jax.tree.map(lambda x: x.astype(jnp.float32), A64)
    b = jnp.ones((4, 3), jnp.float32)

    @jax.jit  # one compilation instead of one per operation
    def everything(A, b):
        L = cholesky(A)
        return L, solve(L, b), matvec(A, b), logdet(L), selected_inverse(L), to_dense(A)

    L, x, Ab, ld, S, dense = everything(A, b)
    assert L.diagonal.dtype == jnp.float32 and L.lower.dtype == jnp.float32
    assert x.dtype == jnp.float32
    assert Ab.dtype == jnp.float32
    assert ld.dtype == jnp.float32
    assert S.diagonal.dtype == jnp.float32 and S.lower.dtype == jnp.float32
    assert dense.dtype == jnp.float32
    np.testing.assert_allclose(
        x, np.linalg.solve(dense_np(A64), np.ones(12)).reshape(4, 3), rtol=1e-4
    )


# ----------------------------------------------------------------------------- arrowhead

# Compiled once per shapes and (static) options: every arrowhead test uses the shapes ARROW and
# the CG options CG where it can (cg_chunk = 3 < p = 5: two chunks, the second padded).
solve_arrow = eqx.filter_jit(arrowhead_solve)
ARROW = (2, 4, 2, 5)  # B, T, n, p
CG = dict(method="cg", cg_preconditioner="schur_diag", cg_chunk=3)


def arrow_problem(rng, B, T, n, p, scale_E=0.3):
    mats = [random_spd(rng, n, T, shift=2.0) for _ in range(B)]
    A = jax.tree.map(lambda *xs: jnp.stack(xs), *mats)
    E = scale_E * rng.standard_normal((B, T, n, p))
    M = rng.standard_normal((p, p))
    D = M @ M.T + (B * T * n * scale_E**2 + 1.0) * np.eye(p)
    r_x = rng.standard_normal((B, T, n))
    r_t = rng.standard_normal(p)
    return mats, A, E, D, r_x, r_t


def schur_part(mats, E):
    """Σ_b E_bᵀ A_b⁻¹ E_b in NumPy."""
    B, T, n, p = E.shape
    return sum(
        E[b].reshape(T * n, p).T @ np.linalg.solve(dense_np(Ab), E[b].reshape(T * n, p))
        for b, Ab in enumerate(mats)
    )


def dense_arrow(mats, E, D, r_x, r_t):
    B, T, n, p = E.shape
    N = B * T * n
    K = np.zeros((N + p, N + p))
    for b, Ab in enumerate(mats):
        sl = slice(b * T * n, (b + 1) * T * n)
        K[sl, sl] = dense_np(Ab)
        K[sl, N:] = E[b].reshape(T * n, p)
        K[N:, sl] = E[b].reshape(T * n, p).T
    K[N:, N:] = D
    sol = np.linalg.solve(K, np.concatenate([r_x.ravel(), r_t]))
    return sol[:N].reshape(B, T, n), sol[N:]


# (1, 1, 1, 1): every dimension at its edge; ARROW: every dimension general. The two other
# general shapes are second oracles of the same code path.
@pytest.mark.parametrize(
    "B,T,n,p",
    [
        (1, 1, 1, 1),
        ARROW,
        (2, 3, 9, 4),  # blocks above UNROLL_MAX
        pytest.param(3, 5, 2, 4, marks=pytest.mark.slow),
        pytest.param(2, 7, 3, 6, marks=pytest.mark.slow),
    ],
)
def test_arrowhead_dense_matches_numpy(B, T, n, p):
    rng = np.random.default_rng(10 + B + T + n + p)
    mats, A, E, D, r_x, r_t = arrow_problem(rng, B, T, n, p)
    sol = solve_arrow(A, E, D, r_x, r_t, method="dense")
    dx_ref, dt_ref = dense_arrow(mats, E, D, r_x, r_t)
    assert sol.method == "dense" and bool(sol.ok) and bool(sol.converged)
    assert int(sol.cg_steps) == 0
    assert rel_err(sol.dx, dx_ref) < 1e-9
    assert rel_err(sol.dtheta, dt_ref) < 1e-9


# "d_diag" and "none" change only the diagonal handed to the same PCG loop (one line each, no
# other code path): second oracles of the CG solve that "schur_diag" (the default, with the chunked
# exact diagonal) checks.
@pytest.mark.parametrize(
    "precond",
    [
        "schur_diag",
        pytest.param("d_diag", marks=pytest.mark.slow),
        pytest.param("none", marks=pytest.mark.slow),
    ],
)
def test_arrowhead_cg_matches_dense(precond):
    rng = np.random.default_rng(3)
    B, T, n, p = ARROW
    _, A, E, D, r_x, r_t = arrow_problem(rng, B, T, n, p)
    dense = solve_arrow(A, E, D, r_x, r_t, method="dense")
    cg = solve_arrow(A, E, D, r_x, r_t, **{**CG, "cg_preconditioner": precond})
    assert cg.method == "cg" and bool(cg.ok) and bool(cg.converged)
    assert 0 < int(cg.cg_steps) <= p
    assert rel_err(cg.dtheta, dense.dtheta) < 1e-6
    assert rel_err(cg.dx, dense.dx) < 1e-6


def test_arrowhead_auto_method():
    rng = np.random.default_rng(4)
    _, A, E, D, r_x, r_t = arrow_problem(rng, *ARROW)
    # The method is static: tracing (no compilation) shows the choice.
    assert jax.eval_shape(lambda: arrowhead_solve(A, E, D, r_x, r_t)).method == "dense"
    sol = solve_arrow(A, E, D, r_x, r_t, dense_max_p=4)
    assert sol.method == "cg" and bool(sol.ok)


# CG only detects non-positive curvature it meets, so a singular (rank-deficient PSD) S is
# only required to be flagged by the dense path.
@pytest.mark.parametrize(
    "kind,method", [("indefinite", "dense"), ("singular", "dense"), ("indefinite", "cg")]
)
def test_arrowhead_bad_schur(kind, method):
    rng = np.random.default_rng(5)
    B, T, n, p = ARROW
    mats, A, E, _, r_x, r_t = arrow_problem(rng, B, T, n, p)
    P = schur_part(mats, E)
    if kind == "indefinite":
        D = P - np.eye(p)  # S = -I
    else:
        v = rng.standard_normal((p, 1))
        D = P + v @ v.T  # S = v v^T, rank one
    sol = solve_arrow(A, E, D, r_x, r_t, **(CG if method == "cg" else dict(method="dense")))
    assert not bool(sol.ok)
    assert np.all(np.isfinite(sol.dx)) and np.all(np.isfinite(sol.dtheta))


def test_arrowhead_bad_state_block():
    rng = np.random.default_rng(6)
    _, A, E, D, r_x, r_t = arrow_problem(rng, *ARROW)
    diag = np.array(A.diagonal)
    diag[1, 2] = -10 * np.eye(2)  # in NumPy: an eager `.at[].set` compiles a program
    A = BlockTridiagonal(diagonal=jnp.asarray(diag), lower=A.lower)
    for kw in (dict(method="dense"), CG):
        sol = solve_arrow(A, E, D, r_x, r_t, **kw)
        assert not bool(sol.ok)
        assert np.all(np.isfinite(sol.dx)) and np.all(np.isfinite(sol.dtheta))


@pytest.mark.parametrize("n", [2, 9])  # elementwise kernels; inverted diagonal blocks
def test_schur_terms_by_forward_passes(n):
    """Σ_b E_bᵀ A_b⁻¹ E_b and Σ_b E_bᵀ A_b⁻¹ r_b from forward substitution alone = dense."""
    rng = np.random.default_rng(70 + n)
    mats, A, E, _, r_x, _ = arrow_problem(rng, 2, 3, n, 4)
    EtE, Etr = jax.jit(lambda A, E, r: schur_terms(*factor(A), E, r))(A, E, r_x)
    assert rel_err(EtE, schur_part(mats, E)) < 1e-10
    ref = sum(
        E[b].reshape(-1, 4).T @ np.linalg.solve(dense_np(Ab), r_x[b].ravel())
        for b, Ab in enumerate(mats)
    )
    assert rel_err(Etr, ref) < 1e-10
