"""The parallel-in-time block-tridiagonal solve and the smoother option.

Oracles: the sequential block-Cholesky solve (``blocktri``) and a dense ``jnp.linalg.solve``;
float64, 1e-10 relative (the requirement is 1e-8; measured ≤ 2e-15 for n ≤ 9, T ≤ 1000). The
default suite keeps two shapes, T = 1 and T = 11 (odd and even lengths in the scans' recursion;
each compiles once, < 2 s); T = 2, 33, 64, 65 and in the thousands, every n = 1..8 and the
smoother run with and without the option (two LM programs compiled, ≈ 4 s) are ``slow``; the
vector right-hand side is checked through ``vmap``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ceemx
from ceemx.inference.smoother import uses_parallel_solve
from ceemx.lib import blocktri
from ceemx.lib.parallel_blocktri import parallel_solve
from ceemx.lib.tree import as_jax
from ceemx.systems import CoupledLorenz, initial_states, random_observation_matrix


def random_spd(rng, n, T, shift=1.0):
    """JᵀJ + shift·I for a random block lower-bidiagonal J (as tests/test_linalg.py)."""
    Jd = rng.standard_normal((T, n, n))
    Jl = rng.standard_normal((T - 1, n, n))
    diag = np.einsum("tji,tjk->tik", Jd, Jd) + shift * np.eye(n)
    diag[:-1] += np.einsum("tji,tjk->tik", Jl, Jl)
    lower = np.einsum("tji,tjk->tik", Jd[1:], Jl)
    return blocktri.BlockTridiagonal(as_jax(diag), as_jax(lower))


def rel_err(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300)


@jax.jit
def _both(A, B):
    """Sequential and parallel solves of a two-column right-hand side, and the dense matrix."""
    return blocktri.cho_solve(A, B), parallel_solve(A, B), blocktri.to_dense(A)


def _check(n, T, dense=True):
    rng = np.random.default_rng(10 * n + T)
    A = random_spd(rng, n, T)
    B = jnp.asarray(rng.standard_normal((T, n, 2)))
    Xs, Xp, Ad = _both(A, B)
    assert Xp.shape == B.shape and Xp.dtype == B.dtype
    assert rel_err(Xp, Xs) < 1e-10
    if dense:
        Xd = np.linalg.solve(np.asarray(Ad), np.asarray(B).reshape(T * n, 2)).reshape(T, n, 2)
        assert rel_err(Xp, Xd) < 1e-10


# (1, 1): no join at all; (2, 11): the associative scans' recursion at three levels, of odd and
# even lengths (11 → 5 → 2 → 1 elements). Each level is traced and compiled separately (T = 64,
# six levels, compiles for about 3 s), so the longer and the other small cases, which run the
# same recursion, are slow.
@pytest.mark.parametrize(
    "n,T",
    [
        (1, 1),
        (2, 11),
        pytest.param(2, 2, marks=pytest.mark.slow),
        pytest.param(2, 64, marks=pytest.mark.slow),
        pytest.param(3, 65, marks=pytest.mark.slow),
        pytest.param(8, 33, marks=pytest.mark.slow),
    ],
)
def test_parallel_solve_equals_sequential_and_dense(n, T):
    _check(n, T)


@pytest.mark.slow  # T in the thousands, every n = 1..8: 16 compilations
@pytest.mark.parametrize("n", range(1, 9))
@pytest.mark.parametrize("T", [1000, 2049])
def test_parallel_solve_long(n, T):
    _check(n, T, dense=T * n <= 4000)


@pytest.mark.slow
def test_parallel_solve_vmaps_over_a_batch():
    rng = np.random.default_rng(0)
    mats = [random_spd(rng, 2, 65) for _ in range(3)]
    A = jax.tree.map(lambda *a: jnp.stack(a), *mats)
    b = jnp.asarray(rng.standard_normal((3, 65, 2)))
    X = jax.jit(jax.vmap(parallel_solve))(A, b)
    Xs = jax.jit(jax.vmap(blocktri.cho_solve))(A, b)
    assert rel_err(X, Xs) < 1e-10


@pytest.mark.slow
def test_parallel_solve_not_positive_definite_is_nan_and_float32_stays():
    rng = np.random.default_rng(1)
    A = random_spd(rng, 2, 17)
    b = jnp.asarray(rng.standard_normal((17, 2)))
    bad = blocktri.BlockTridiagonal(A.diagonal.at[5].multiply(-1.0), A.lower)
    assert bool(jnp.any(jnp.isnan(jax.jit(parallel_solve)(bad, b))))
    A32 = jax.tree.map(lambda a: a.astype(jnp.float32), A)
    x32 = jax.jit(parallel_solve)(A32, b.astype(jnp.float32))
    assert x32.dtype == jnp.float32
    assert rel_err(x32, blocktri.cho_solve(A, b)) < 1e-4


def test_time_parallel_option():
    assert not uses_parallel_solve(False, 10**6)
    assert uses_parallel_solve(True, 2)
    # "auto" chooses the sequential solve on CPU, where it always measured faster
    assert uses_parallel_solve("auto", 10**6) == (jax.default_backend() != "cpu")
    with pytest.raises(ValueError, match="time_parallel"):
        ceemx.LMSmoother(time_parallel="yes")


@pytest.mark.slow  # two smoother compilations, ≈ 4 s
def test_smoothing_equal_with_and_without_time_parallel():
    """One Lorenz attractor (n = 3), B = 2, T = 32, from perturbed states.

    Each LM step solves the same system; the two solves agree to ~1e-15 relative, so the two runs
    take the same accept/reject decisions and iterations, and the converged states differ by the
    rounding of the last steps amplified by the Gauss–Newton conditioning (measured ≲ 1e-12); 1e-9
    leaves room without hiding a wrong solve (a wrong step would not converge to the same point
    in the same iterations).
    """
    keys = jax.random.split(jax.random.PRNGKey(3), 4)
    C = random_observation_matrix(keys[0], 1)
    system = CoupledLorenz(
        jnp.full(1, 10.0), jnp.full(1, 28.0), jnp.full(1, 8.0 / 3.0), C,
        process_noise=0.05, obs_noise=0.1,
    )  # fmt: skip
    truth, data = ceemx.simulate(system, keys[1], initial_states(keys[2], 2, 1), 32)
    x_init = truth + 0.3 * jax.random.normal(keys[3], truth.shape)
    seq = ceemx.smooth(system, data, x_init, ceemx.LMSmoother(rtol=1e-12))
    par = ceemx.smooth(system, data, x_init, ceemx.LMSmoother(rtol=1e-12, time_parallel=True))
    assert bool(jnp.all(seq.converged)) and bool(jnp.all(par.converged))
    np.testing.assert_array_equal(seq.iterations, par.iterations)
    assert rel_err(par.states, seq.states) < 1e-9
    np.testing.assert_allclose(par.objective, seq.objective, rtol=1e-12)


@pytest.mark.slow  # a fresh process compiles both solves at two lengths (≈ 10–15 s)
def test_benchmark_smoke(tmp_path):
    import json
    import pathlib
    import subprocess
    import sys

    root = pathlib.Path(__file__).resolve().parents[1]
    out = tmp_path / "pit.json"
    script = root / "benchmarks" / "parallel_in_time.py"
    cmd = [sys.executable, str(script), "--smoke", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(out.read_text())
    assert [c["T"] for c in res["cases"]] == [64, 257]
    assert all(c["rel_diff"] < 1e-10 for c in res["cases"])
