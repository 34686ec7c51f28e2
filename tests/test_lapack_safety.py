"""No two batched LAPACK calls of one compiled program may run at once (docs/known_issues.md).

jaxlib 0.10.2's CPU LAPACK kernels fan a batch out over XLA's intra-op pool and block; two such
calls running concurrently deadlock a 2-core machine (Laplace EM at T = 25 000 hung in its
cubature step). Here: the elementwise kernels of ``ceemx.lib.dense`` that replace batched LAPACK
calls for small blocks (against LAPACK/NumPy), ``after`` (value, gradient, and that it orders
where ``optimization_barrier`` does not), the HLO audit on known patterns, and the audit on the
compiled Laplace EM programs (default suite, deterministic). Marked ``slow``: the audit of a
representative set of every solver's programs (``.ci/check_lapack_concurrency.py``) and the
long-record fits in subprocesses under a timeout (a hang fails them).
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.identification.learning.expected import cubature_points
from ceemx.inference.posterior import E_STEP_SMOOTHER, gaussian_posterior
from ceemx.lib import dense
from ceemx.lib.cubature import psd_sqrt, sigma_points
from ceemx.lib.tree import as_jax, trace_numbers

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / ".ci"))  # the HLO audit is CI tooling, not part of the library

from hlo_audit import compiled_hlo, lapack_calls, lapack_concurrency  # noqa: E402


def _spd(rng, shape, d, jitter=0.1):
    M = rng.normal(size=(*shape, d, d))
    return M @ np.swapaxes(M, -1, -2) + jitter * np.eye(d)


@pytest.mark.parametrize("d", [3, 9])  # unrolled (d ≤ UNROLL_MAX = 8) and looped
def test_elementwise_kernels_match_lapack(d):
    """Cholesky, triangular and Cholesky solves, Jacobi eigh: batched, against LAPACK/NumPy."""
    rng = np.random.default_rng(d)
    A = _spd(rng, (3, 4), d)
    b, B = rng.normal(size=(3, 4, d)), rng.normal(size=(3, 4, d, 2))
    S = A - 2.0 * np.eye(d)  # symmetric, indefinite

    @jax.jit  # one program, the LAPACK gradient oracle included
    def kernels(A, b, B, S):
        L = dense.cholesky(A)
        w, V = dense.eigh(S)
        grad = jax.grad(lambda a: jnp.sum(dense.cholesky(a) ** 3))(A[0, 0])
        g_ref = jax.grad(lambda a: jnp.sum(jnp.linalg.cholesky(a) ** 3))(A[0, 0])
        return (
            L,
            dense.solve_triangular(L, b),
            dense.solve_triangular(L, B, trans=True),
            dense.cho_solve(L, B),
            dense.cholesky(-A),
            (w, V),
            (grad, g_ref),
        )

    outputs = kernels(*map(as_jax, (A, b, B, S)))
    L, x, X, Y, bad, (w, V), (g, g_ref) = jax.tree.map(np.asarray, outputs)  # checked in NumPy
    np.testing.assert_allclose(L, np.linalg.cholesky(A), atol=1e-13)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", L, x), b, atol=1e-12)
    np.testing.assert_allclose(np.swapaxes(L, -1, -2) @ X, B, atol=1e-12)
    np.testing.assert_allclose(A @ Y, B, atol=1e-10)
    assert np.all(np.isnan(bad))  # not positive definite: NaN, as LAPACK's
    np.testing.assert_allclose(V @ (w[..., None] * np.swapaxes(V, -1, -2)), S, atol=1e-12)
    eye = np.broadcast_to(np.eye(d), S.shape)
    np.testing.assert_allclose(np.swapaxes(V, -1, -2) @ V, eye, atol=1e-13)
    np.testing.assert_allclose(np.sort(w, -1), np.linalg.eigvalsh(S), atol=1e-12)
    np.testing.assert_allclose(g, g_ref, atol=1e-10)


def test_psd_square_root_of_singular_pair_covariances():
    """The cubature root exists for the singular pair covariance of a deterministic transition."""
    rng = np.random.default_rng(0)
    P = _spd(rng, (50,), 2, jitter=1e-6) * 1e-4
    F = np.array([[1.0, 0.1], [-0.4, 0.95]])
    pair = np.concatenate(
        [np.concatenate([P, P @ F.T], -1), np.concatenate([F @ P, F @ P @ F.T], -1)], -2
    )  # rank 2 of 4, rounding-level indefinite
    R, pts = jax.jit(lambda c: (psd_sqrt(c), sigma_points(jnp.zeros(c.shape[:-1]), c)))(pair)
    R, pts = np.asarray(R), np.asarray(pts)  # checked in NumPy: eager JAX compiles each operation
    assert np.all(np.isfinite(R))
    assert jax.eval_shape(dense.cholesky, jnp.asarray(pair)).shape == R.shape
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), pair, atol=1e-18)
    np.testing.assert_allclose(np.einsum("tki,tkj->tij", pts, pts) / 8, pair, atol=1e-18)


def test_after_keeps_the_value_and_the_gradient():
    x = jnp.array([-0.0, 1.5, jnp.nan, jnp.inf])

    @jax.jit  # one program (as the library uses it) instead of one per eager operation
    def value_and_grads(x, d1, d2):
        grads = jax.grad(lambda a, b: jnp.sum(dense.after(a, b) ** 2), argnums=(0, 1))(
            jnp.ones(3), jnp.ones(2)
        )
        return dense.after(x, d1, d2), grads

    out, (gx, gd) = value_and_grads(x, jnp.array([jnp.nan, 2.0]), jnp.array([-3.0]))
    np.testing.assert_array_equal(gx, 2 * jnp.ones(3))
    np.testing.assert_array_equal(gd, jnp.zeros(2))


def _two_roots(order):
    def root(m):
        w, v = jnp.linalg.eigh(m)
        return (v * jnp.sqrt(jnp.clip(w, 0.0))[..., None, :]) @ jnp.swapaxes(v, -1, -2)

    def f(a, b):
        ra = root(a)
        if order == "after":
            b = dense.after(b, ra)
        elif order == "barrier":
            b, ra = jax.lax.optimization_barrier((b, ra))
        return ra, root(b)

    return jax.jit(f)


def test_audit_finds_concurrent_batched_lapack_calls():
    """Independent batched calls are found; `after` orders them, an optimization barrier does not
    (it aliases its operands and emits no operation); single-matrix calls do not count."""
    a = jnp.broadcast_to(jnp.eye(3), (50, 3, 3)) * 2.0
    found = {o: lapack_concurrency(compiled_hlo(_two_roots(o), a, a)) for o in (None, "after")}
    assert len(found[None]) == 1 and "lapack_dsyevd_ffi[50]" in found[None][0].first_targets
    assert found["after"] == []
    assert len(lapack_concurrency(compiled_hlo(_two_roots("barrier"), a, a))) == 1
    one = compiled_hlo(_two_roots(None), a[0], a[0])  # batch 1: jaxlib runs it inline
    assert lapack_concurrency(one) == [] and len(lapack_concurrency(one, min_batch=1)) == 1

    def looped(a, b):  # a LAPACK call inside a loop body is concurrent with one outside
        inner = jax.lax.fori_loop(0, 3, lambda i, m: jnp.linalg.cholesky(m + i), a)
        return inner, jnp.linalg.cholesky(b)

    hlo = compiled_hlo(jax.jit(looped), a, a)
    found = lapack_concurrency(hlo)
    assert len(found) == 1 and len(lapack_calls(hlo)) == 2


def _linear_problem(B=2, T=40):
    """A LinearSystem with full noise covariances, a prior and a missing value (the most
    LAPACK-prone setting before the fix: noise whitening, Kalman updates, filled moments)."""
    rng = np.random.default_rng(0)
    y = rng.normal(size=(B, T, 2))
    mask = np.ones_like(y, dtype=bool)
    mask[:, 5, 0] = False
    data = ceemx.Trajectories(jnp.asarray(y), mask=jnp.asarray(mask))
    prior = ceemx.GaussianPrior(jnp.zeros(2), ceemx.CholeskyGaussian(cov=jnp.eye(2)))
    system = ceemx.systems.LinearSystem(
        jnp.array([[0.9, 0.2], [-0.15, 0.8]]),
        jnp.array([[1.0, 0.3], [0.2, 1.0]]),
        process_noise=ceemx.CholeskyGaussian(cov=jnp.array([[0.05, 0.01], [0.01, 0.04]])),
        obs_noise=ceemx.CholeskyGaussian(cov=jnp.array([[0.1, 0.02], [0.02, 0.2]])),
        initial_prior=prior,
    )
    return system, data


@pytest.mark.slow
def test_laplace_e_step_and_cubature_have_no_concurrent_lapack_calls():
    """The compiled cubature step (two batched eighs: the hang this guards against) and E-step (MAP
    smoothing, selected inverse, log-det) of Laplace EM: no two batched LAPACK calls independent
    of each other. Compiled, not run; the other programs: the ``slow`` audit below."""
    system, data = _linear_problem()
    B, T = data.y.shape[:2]
    x0 = jnp.zeros((B, T, 2))
    cov = jnp.broadcast_to(0.1 * jnp.eye(2), (B, T, 2, 2))
    smoother = trace_numbers(E_STEP_SMOOTHER, x0.dtype)
    programs = {
        "cubature_points": (cubature_points, x0, cov, cov[:, 1:]),
        "gaussian_posterior": (gaussian_posterior, smoother, system, x0, data),
    }
    for name, (fn, *args) in programs.items():
        assert lapack_concurrency(compiled_hlo(fn, *args), module=name) == [], name


@pytest.mark.slow
def test_library_programs_have_no_concurrent_lapack_calls():
    """Every solver's fit, smoothing, filters, learners, evaluation and covariances (1–5 min)."""
    out = subprocess.run(
        [sys.executable, str(ROOT / ".ci" / "check_lapack_concurrency.py")],
        capture_output=True,
        text=True,
        timeout=1500,
        cwd=ROOT,
    )
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-4000:]
    assert "0 concurrent pair(s)" in out.stdout


_LONG_FIT = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {bench!r})
    import jax
    jax.config.update("jax_enable_x64", True)
    from laplace_long_record import laplace_fit, problem
    start, data = problem({T})
    for rep in range({reps}):
        r = laplace_fit(start, data, max_epochs={epochs})
        print("fit", rep, len(r.history), float(r.system.k), flush=True)
    """
)


def _run_long_fits(T: int, reps: int, epochs: int, timeout: int) -> str:
    code = _LONG_FIT.format(bench=str(ROOT / "benchmarks"), T=T, reps=reps, epochs=epochs)
    try:
        out = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=timeout,
            env={**os.environ, "PYTHONWARNINGS": "ignore"},
        )
    except subprocess.TimeoutExpired as e:  # the deadlock: the process never returns
        pytest.fail(f"Laplace EM at T = {T} did not return within {timeout} s (hang): {e.stdout}")
    assert out.returncode == 0, out.stderr[-4000:]
    return out.stdout


@pytest.mark.slow
def test_laplace_em_long_record_returns():
    """Laplace EM with learned noise on T = 25 000 samples returns: 3 fits (≈ 90 cubature and
    E-step programs each, which hung in ~4 % of calls with concurrent LAPACK calls) under a
    timeout."""
    out = _run_long_fits(25_000, reps=3, epochs=10, timeout=900)
    assert out.count("fit ") == 3


@pytest.mark.slow
def test_laplace_em_100k_record_returns():
    out = _run_long_fits(100_000, reps=1, epochs=10, timeout=1200)
    assert out.count("fit ") == 1
