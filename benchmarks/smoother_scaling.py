"""Scaling of the Levenberg–Marquardt smoother (`ceemx.smooth`) on coupled Lorenz problems.

Measures, per case, the compile time (first call minus steady state) and the steady-state time per
smoother iteration (median over repeated calls, divided by the iteration count), sweeping
independently

* T ∈ {128, …, 4096}        (B = 8, K = 6),
* B ∈ {1, 2, …, 64}          (T = 128, K = 6),
* K ∈ {1, 2, 5, 10, 20}      (T = 128, B = 8; n = 3K, m = 3K − 2),

and fits log–log slopes of the time per iteration against T, B and n. The solver runs exactly
``--steps`` iterations (``rtol = atol = 0``); this is checked from ``sol.iterations``. Each case
runs in a fresh Python process by default (``--no-isolate`` to share one): after large cases, later
small ones were seen to run several times slower in the same process.

Usage::

    python benchmarks/smoother_scaling.py                  # full sweep
    python benchmarks/smoother_scaling.py --quick          # small subset, 1 repeat
    python benchmarks/smoother_scaling.py --out results.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ceemx  # noqa: E402
from ceemx.systems import (  # noqa: E402
    CoupledLorenz,
    initial_states,
    random_coupling,
    random_observation_matrix,
)

FULL = {
    "T": [128, 256, 512, 1024, 2048, 4096],
    "B": [1, 2, 4, 8, 16, 32, 64],
    "K": [1, 2, 5, 10, 20],
}
QUICK = {
    "T": [128, 256, 512, 1024],
    "B": [1, 2, 4, 8, 16],
    "K": [1, 2, 5, 10],
}
BASE = {"T": 128, "B": 8, "K": 6}
PERTURBATION = 0.1  # x_init = truth + PERTURBATION · N(0, 1)


def make_problem(T: int, B: int, K: int, seed: int = 0):
    """Truth, observations and a perturbed initial guess for one coupled Lorenz case."""
    kH, kC, kx0, ksim, kpert = jax.random.split(jax.random.PRNGKey(seed), 5)
    H = random_coupling(kH, K)
    C = random_observation_matrix(kC, K)
    ones = jnp.ones(K, jnp.float64)
    system = CoupledLorenz(
        10.0 * ones, 28.0 * ones, (8.0 / 3.0) * ones, C, H=H, process_noise=0.01, obs_noise=0.01
    )
    x0 = initial_states(kx0, B, K)
    truth, data = ceemx.simulate(system, ksim, x0, T, process_noise=False)
    x_init = truth + PERTURBATION * jax.random.normal(kpert, truth.shape, truth.dtype)
    return system, data, jax.block_until_ready(x_init)


def time_case(
    T: int, B: int, K: int, steps: int, repeats: int, min_time: float = 0.0, max_repeats: int = 20
) -> dict:
    """Time one case: ``repeats`` steady-state calls at least, more (≤ ``max_repeats``) until
    they add up to ``min_time`` seconds."""
    system, data, x_init = make_problem(T, B, K)
    solver = ceemx.LMSmoother(max_steps=steps, rtol=0.0, atol=0.0)

    def call():
        t0 = time.perf_counter()
        sol = ceemx.smooth(system, data, x_init, solver)
        jax.block_until_ready(sol)
        return time.perf_counter() - t0, sol

    first, sol = call()
    iters = np.asarray(sol.iterations)
    status = np.asarray(sol.status)
    if not np.all(iters == steps):
        raise RuntimeError(
            f"T={T} B={B} K={K}: expected {steps} iterations, got {iters.tolist()} "
            f"(status {status.tolist()})"
        )
    if not np.all(np.isfinite(np.asarray(sol.objective))):
        raise RuntimeError(f"T={T} B={B} K={K}: non-finite objective")
    load_before = os.getloadavg()[0]
    runs: list[float] = []
    while len(runs) < repeats or (sum(runs) < min_time and len(runs) < max_repeats):
        runs.append(call()[0])
    steady = statistics.median(runs)
    per_iter = steady / steps
    return {
        "T": T,
        "B": B,
        "K": K,
        "n": 3 * K,
        "m": 3 * K - 2,
        "iterations": steps,
        "first_call_s": first,
        "steady_call_s": steady,
        "steady_runs_s": runs,
        "compile_s": first - steady,
        "per_iter_s": per_iter,
        "per_iter_per_traj_step_s": per_iter / (B * T),
        "per_iter_min_s": min(runs) / steps,
        "loadavg_1min": [load_before, os.getloadavg()[0]],
    }


def time_case_isolated(T: int, B: int, K: int, steps: int, repeats: int, min_time: float) -> dict:
    """:func:`time_case` in a fresh Python process (no allocator or cache state from before)."""
    cmd = [
        sys.executable,
        os.path.abspath(__file__),
        "--case",
        str(T),
        str(B),
        str(K),
        "--steps",
        str(steps),
        "--repeats",
        str(repeats),
        "--min-time",
        str(min_time),
    ]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def slope(xs, ys) -> float:
    return float(np.polyfit(np.log(np.asarray(xs, float)), np.log(np.asarray(ys, float)), 1)[0])


def markdown_table(rows: list[dict]) -> str:
    head = (
        "| T | B | K | n | m | compile (s) | steady call, median (s) | per iteration, median (ms) "
        "| per iteration, min (ms) | per iteration per trajectory-step (µs) |"
    )
    lines = [head, "|" + "---:|" * 10]
    for r in rows:
        lines.append(
            f"| {r['T']} | {r['B']} | {r['K']} | {r['n']} | {r['m']} | {r['compile_s']:.2f} "
            f"| {r['steady_call_s']:.4f} | {1e3 * r['per_iter_s']:.2f} "
            f"| {1e3 * r['per_iter_min_s']:.2f} "
            f"| {1e6 * r['per_iter_per_traj_step_s']:.2f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--quick", action="store_true", help="small subset (T ≤ 1024, B ≤ 16, K ≤ 10), 1 repeat"
    )
    p.add_argument("--out", type=str, default=None, help="write all numbers as JSON to this path")
    p.add_argument("--steps", type=int, default=5, help="LM iterations per call (default 5)")
    p.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="minimum steady-state calls per case (default 3; 1 with --quick)",
    )
    p.add_argument(
        "--min-time",
        type=float,
        default=None,
        help="keep repeating cheap cases (up to 20 calls) until the steady-state calls add up "
        "to this many seconds (default 1.0; 0 with --quick)",
    )
    p.add_argument(
        "--no-isolate",
        action="store_true",
        help="time all cases in this process instead of one fresh process per case",
    )
    p.add_argument("--case", type=int, nargs=3, metavar=("T", "B", "K"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    grid = QUICK if args.quick else FULL
    repeats = args.repeats if args.repeats is not None else (1 if args.quick else 3)
    min_time = args.min_time if args.min_time is not None else (0.0 if args.quick else 1.0)
    if args.case:  # worker mode of time_case_isolated: one case, JSON on the last line of stdout
        print(
            json.dumps(time_case(*args.case, steps=args.steps, repeats=repeats, min_time=min_time))
        )
        return {}
    timer = time_case if args.no_isolate else time_case_isolated
    cache: dict[tuple[int, int, int], dict] = {}
    sweeps: dict[str, list[dict]] = {}
    slopes: dict[str, float] = {}  # fitted on the median time per iteration
    slopes_min: dict[str, float] = {}  # fitted on the minimum (less sensitive to other load)
    t_start = time.perf_counter()
    print(
        f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs; "
        f"{args.steps} LM iterations per call, median of ≥{repeats} steady-state call(s) "
        f"(≥{min_time:g} s per case), "
        f"{'one process' if args.no_isolate else 'a fresh process per case'}; "
        f"1-min load average {os.getloadavg()[0]:.2f}\n"
    )
    for var in ("T", "B", "K"):
        rows = []
        for value in grid[var]:
            cfg = dict(BASE, **{var: value})
            key = (cfg["T"], cfg["B"], cfg["K"])
            if key not in cache:
                cache[key] = timer(*key, steps=args.steps, repeats=repeats, min_time=min_time)
            rows.append(cache[key])
        sweeps[var] = rows
        xvar = "n" if var == "K" else var
        slopes[xvar] = slope([r[xvar] for r in rows], [r["per_iter_s"] for r in rows])
        slopes_min[xvar] = slope([r[xvar] for r in rows], [r["per_iter_min_s"] for r in rows])
        fixed = ", ".join(f"{k}={v}" for k, v in BASE.items() if k != var)
        print(f"### Sweep over {var} ({fixed})\n")
        print(markdown_table(rows))
        print(
            f"\nlog–log slope of time per iteration vs {xvar}: {slopes[xvar]:.2f} "
            f"(median; {slopes_min[xvar]:.2f} from the minimum)\n",
            flush=True,
        )
    total = time.perf_counter() - t_start
    print(
        "Slopes of median time per iteration: "
        + ", ".join(f"{k}: {v:.2f}" for k, v in slopes.items())
    )
    print(
        "Slopes of minimum time per iteration: "
        + ", ".join(f"{k}: {v:.2f}" for k, v in slopes_min.items())
    )
    print(f"Total wall time: {total:.1f} s; 1-min load average at the end {os.getloadavg()[0]:.2f}")

    result = {
        "config": {
            "quick": args.quick,
            "steps": args.steps,
            "repeats": repeats,
            "isolated": not args.no_isolate,
            "min_time_s": min_time,
            "base": BASE,
            "grid": grid,
            "perturbation": PERTURBATION,
            "dtype": "float64",
        },
        "environment": {
            "jax": jax.__version__,
            "ceemx": ceemx.__version__,
            "backend": jax.devices()[0].platform,
            "device": str(jax.devices()[0]),
            "cpu_count": os.cpu_count(),
            "python": platform.python_version(),
            "machine": platform.machine(),
        },
        "sweeps": sweeps,
        "slopes": slopes,
        "slopes_min": slopes_min,
        "total_wall_s": total,
    }
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)
        print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
