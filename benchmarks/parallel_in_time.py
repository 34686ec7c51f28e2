"""Sequential vs parallel-in-time block-tridiagonal solves.

Backs ``benchmarks/README.md`` (parallel in time) and ``docs/decisions.md``: on CPU the
associative-scan solve never measured faster, so ``LMSmoother(time_parallel="auto")`` stays
sequential there. Writes ``benchmarks/results/parallel_in_time.json``.

What is measured (float64, one SPD block-tridiagonal matrix, one right-hand side, on the default
JAX backend): per (T, n), the time of one solve of ``A x = b`` by

* ``sequential``: ``blocktri.solve(blocktri.cholesky(A), b)`` — what one smoother iteration does;
* ``parallel``: ``parallel_blocktri.parallel_solve(A, b)`` — two associative scans.

Each is jitted; compile time = the first call (compile + run) − the median steady call, reported
apart; the steady time is the median of ``--reps`` (≥ 3) calls; the relative difference of the
two solutions is recorded; ``os.getloadavg()`` and ``uptime`` before and after the run.

Usage::

    python benchmarks/parallel_in_time.py                       # T 1e3, 1e4, 1e5; n 2, 6
    python benchmarks/parallel_in_time.py --smoke --out x.json  # seconds
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import subprocess
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from ceemx.lib import blocktri  # noqa: E402
from ceemx.lib.parallel_blocktri import parallel_solve  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def random_spd(rng: np.random.Generator, n: int, T: int) -> blocktri.BlockTridiagonal:
    """JᵀJ + I for a random block lower-bidiagonal J (as tests/test_linalg.py)."""
    Jd = rng.standard_normal((T, n, n))
    Jl = rng.standard_normal((T - 1, n, n))
    diag = np.einsum("tji,tjk->tik", Jd, Jd) + np.eye(n)
    diag[:-1] += np.einsum("tji,tjk->tik", Jl, Jl)
    lower = np.einsum("tji,tjk->tik", Jd[1:], Jl)
    return blocktri.BlockTridiagonal(jax.numpy.asarray(diag), jax.numpy.asarray(lower))


@jax.jit
def sequential(A, b):
    """The smoother's sequential solve: block Cholesky, forward and backward scans."""
    return blocktri.solve(blocktri.cholesky(A), b)


@jax.jit
def parallel(A, b):
    """The associative-scan solve."""
    return parallel_solve(A, b)


def _time(fn, A, b, reps: int) -> tuple[dict, jax.Array]:
    t0 = time.perf_counter()
    x = jax.block_until_ready(fn(A, b))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(A, b))
        runs.append(time.perf_counter() - t0)
    med = statistics.median(runs)
    return {
        "first_s": first,
        "compile_s": max(first - med, 0.0),
        "median_s": med,
        "runs_s": runs,
    }, x


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, timeout=5).stdout.strip()
    except OSError:  # pragma: no cover
        return ""


def main(argv: list[str] | None = None) -> dict:
    """Run the grid, print a table and write the JSON."""
    ap = argparse.ArgumentParser(description="Sequential vs parallel-in-time block solves.")
    ap.add_argument("--T", type=int, nargs="+", default=[1000, 10_000, 100_000])
    ap.add_argument("--n", type=int, nargs="+", default=[2, 6])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--smoke", action="store_true", help="tiny grid (T 64, 257; n 2), 3 reps")
    ap.add_argument("--out", default=None, help="JSON path (default results/parallel_in_time.json)")
    args = ap.parse_args(argv)
    if args.smoke:
        args.T, args.n, args.reps = [64, 257], [2], 3
        if args.out is None:
            ap.error("--smoke needs --out (the committed results are the full grid's)")
    out = pathlib.Path(args.out or ROOT / "benchmarks" / "results" / "parallel_in_time.json")
    reps = max(args.reps, 3)
    res: dict = {
        "backend": jax.default_backend(),
        "device": str(jax.devices()[0]),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "reps": reps,
        "loadavg_before": os.getloadavg(),
        "uptime_before": _uptime(),
        "cases": [],
    }
    print(
        f"{'T':>7} {'n':>2} {'seq ms':>9} {'par ms':>9} {'par/seq':>7} "
        f"{'seq comp s':>10} {'par comp s':>10} {'rel diff':>9} {'load':>5}"
    )
    for n in args.n:
        for T in args.T:
            rng = np.random.default_rng(1000 * n + T)
            A = random_spd(rng, n, T)
            b = jax.numpy.asarray(rng.standard_normal((T, n)))
            load = os.getloadavg()[0]
            seq, xs = _time(sequential, A, b, reps)
            par, xp = _time(parallel, A, b, reps)
            diff = float(np.linalg.norm(np.asarray(xp - xs)) / np.linalg.norm(np.asarray(xs)))
            case = {
                "T": T,
                "n": n,
                "sequential": seq,
                "parallel": par,
                "rel_diff": diff,
                "ratio": par["median_s"] / seq["median_s"],
                "load1": load,
            }
            res["cases"].append(case)
            print(
                f"{T:>7} {n:>2} {1e3 * seq['median_s']:>9.3f} {1e3 * par['median_s']:>9.3f} "
                f"{case['ratio']:>7.2f} {seq['compile_s']:>10.2f} {par['compile_s']:>10.2f} "
                f"{diff:>9.1e} {load:>5.2f}",
                flush=True,
            )
    res["loadavg_after"] = os.getloadavg()
    res["uptime_after"] = _uptime()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return res


if __name__ == "__main__":
    main()
