"""Our bounded PCG on the arrowhead Schur complement against ``lineax.CG``.

Usage: ``python benchmarks/cg_choice.py``. Builds a random arrowhead system with the Figure-3
shapes (B = 8, T = 128, n = 18, P = 342 parameters), forms the Schur complement S matrix-free
(as :func:`ceemx.lib.arrowhead_solve` does) and solves S δθ = r with (a) the PCG in
``ceemx.lib.arrowhead`` and (b) ``lineax.linear_solve(..., lineax.CG)`` with the same Jacobi
preconditioner and tolerance. Reports the relative error against a dense solve and the median
steady-state time of 5 calls each (compile apart), alternating the two. Then an indefinite S
(an SPD A with a D too small): ours must flag non-positive curvature; lineax has no such flag.

Backs: ``docs/decisions.md`` (our own PCG rather than ``lineax.CG``).
"""

from __future__ import annotations

import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import lineax as lx  # noqa: E402
import numpy as np  # noqa: E402

from ceemx.lib import arrowhead as ah  # noqa: E402
from ceemx.lib.blocktri import BlockTridiagonal, cholesky  # noqa: E402


def problem(rng, B=8, T=128, n=18, P=342, d_shift=1.0):
    Jd = rng.standard_normal((B, T, n, n)) / np.sqrt(n)
    Jl = rng.standard_normal((B, T - 1, n, n)) / np.sqrt(n)
    diag = np.einsum("btji,btjk->btik", Jd, Jd) + np.eye(n)
    diag[:, :-1] += np.einsum("btji,btjk->btik", Jl, Jl)
    lower = np.einsum("btji,btjk->btik", Jd[:, 1:], Jl)
    A = BlockTridiagonal(jnp.asarray(diag), jnp.asarray(lower))
    E = jnp.asarray(rng.standard_normal((B, T, n, P)) * 0.1)
    G = rng.standard_normal((P, P)) / np.sqrt(P)
    D = jnp.asarray(G @ G.T * d_shift + d_shift * np.eye(P))
    return A, E, D, jnp.asarray(rng.standard_normal(P))


def pieces(A, E, D):
    L = jax.vmap(cholesky)(A)

    def S_mv(v):
        Ev = jnp.einsum("btnp,p->btn", E, v)
        return D @ v - jnp.sum(jnp.einsum("btnp,btn->bp", E, ah._solve_b(L, Ev)), axis=0)

    d = jnp.diagonal(D) - ah._schur_diag(L, E, 64)
    return S_mv, jnp.where(d > 0, 1.0 / jnp.where(d > 0, d, 1.0), 1.0)


@jax.jit
def ours(A, E, D, r):
    S_mv, m_inv = pieces(A, E, D)
    x, steps, conv, broken = ah.pcg(S_mv, r, m_inv, 1e-10, r.shape[0])
    return x, steps, broken


@jax.jit
def theirs(A, E, D, r):
    S_mv, m_inv = pieces(A, E, D)
    op = lx.FunctionLinearOperator(
        S_mv, jax.ShapeDtypeStruct(r.shape, r.dtype), tags=lx.positive_semidefinite_tag
    )
    pre = lx.TaggedLinearOperator(lx.DiagonalLinearOperator(m_inv), lx.positive_semidefinite_tag)
    sol = lx.linear_solve(
        op,
        r,
        lx.CG(rtol=1e-10, atol=0.0, max_steps=r.shape[0]),
        options={"preconditioner": pre},
        throw=False,
    )
    return sol.value, sol.stats["num_steps"], sol.result != lx.RESULTS.successful


def dense_S(A, E, D):
    L = jax.vmap(cholesky)(A)
    Z = ah._solve_b(L, E)
    return D - jnp.sum(jnp.einsum("btnp,btnq->bpq", E, Z), axis=0)


def main():
    rng = np.random.default_rng(0)
    A, E, D, r = problem(rng)
    ref = np.linalg.solve(np.asarray(dense_S(A, E, D)), np.asarray(r))
    for f in (ours, theirs):
        t0 = time.perf_counter()
        jax.block_until_ready(f(A, E, D, r))
        print(f"{f.__name__}: compile + first call {time.perf_counter() - t0:.2f} s")
    times = {"ours": [], "theirs": []}
    errs = {}
    for _ in range(5):
        for name, f in (("ours", ours), ("theirs", theirs)):
            t0 = time.perf_counter()
            x, steps, flag = jax.block_until_ready(f(A, E, D, r))
            times[name].append(time.perf_counter() - t0)
            err = np.linalg.norm(np.asarray(x) - ref) / np.linalg.norm(ref)
            errs[name] = (err, int(steps))
    for name, (err, steps) in errs.items():
        print(f"{name}: rel. error vs dense {err:.1e}, CG steps {steps}")
    for name, t in times.items():
        runs = [round(v * 1e3, 1) for v in t]
        print(f"{name}: median {statistics.median(t) * 1e3:.1f} ms (runs {runs})")
    # Indefinite S: D far too small for the border.
    A, E, D, r = problem(rng, d_shift=1e-3)
    S = np.asarray(dense_S(A, E, D))
    print(f"indefinite case: min eig(S) = {np.linalg.eigvalsh(S).min():.3g}")
    for f in (ours, theirs):
        x, steps, flag = f(A, E, D, r)
        finite = bool(np.all(np.isfinite(x)))
        name = f.__name__
        print(f"  {name}: flagged failure = {bool(flag)}, finite = {finite}, steps {int(steps)}")


if __name__ == "__main__":
    main()
