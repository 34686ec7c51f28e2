"""Smoothing, the Laplace E-step and the gradient of Q on one long record, T interleaved.

``scaling.py --only long`` measures each (T, method) in a fresh process, so on a shared machine
whose load swings (1-min load 20–28 during the 2026-11-25 run) each T meets a different load.
Here every T is compiled first, then the calls cycle over T, ``--reps`` times, so the load a
rep meets is shared by every T; the median per T and the log–log fit against T are written.

Timed (mass–spring–damper of ``laplace_long_record.py``, start θ): ``ceemx.smooth`` with 5 LM
iterations per call, the Laplace posterior (``gaussian_posterior``: MAP to rtol 1e-14 from the
previous MAP, selected inverse, log-det) and the value and θ-gradient of Q (the quasi-Newton
epoch's M-step part).

    python benchmarks/probes/long_interleaved.py [--T 10000 31623 100000] [--reps 5] [--out F]

Backs: ``benchmarks/README.md`` ("Long records").
"""

import argparse
import json
import os
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)
HERE = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(HERE))
import laplace_long_record as llr  # noqa: E402
import scaling  # noqa: E402

import ceemx  # noqa: E402
from ceemx.identification.problem import FitProblem  # noqa: E402
from ceemx.identification.solvers.laplace_qn import q_derivatives  # noqa: E402
from ceemx.inference.posterior import E_STEP_SMOOTHER, gaussian_posterior  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402


def main() -> None:
    """Run the interleaved timings and write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=int, nargs="+", default=[10000, 31623, 100000])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", default=str(HERE / "results" / "long_interleaved.json"))
    args = ap.parse_args()
    solver = ceemx.LMSmoother(max_steps=5, rtol=0.0, atol=0.0)
    estep = trace_numbers(E_STEP_SMOOTHER, jnp.float64)
    calls = {}
    for T in args.T:
        start, data = llr.problem(T)
        problem, theta = FitProblem.create(
            start, data, trainable=lambda s: (s.k, s.c, s.process_noise, s.obs_noise)
        )
        x0 = jnp.zeros((1, T, 2))
        post = gaussian_posterior(estep, start, x0, data)
        calls[T] = {
            "smooth_5_iterations": lambda s=start, d=data, x=x0: ceemx.smooth(s, d, x, solver),
            "laplace_posterior": lambda s=start, d=data, x=post.states: gaussian_posterior(
                estep, s, x, d
            ),
            "q_value_and_gradient": lambda p=problem, t=theta, e=post: q_derivatives(
                p, t, e, hessian=False
            ),
        }
        for f in calls[T].values():
            jax.block_until_ready(f())
    times = {T: {k: [] for k in calls[T]} for T in args.T}
    loads = []
    for _ in range(args.reps):
        loads.append(os.getloadavg()[0])
        for T in args.T:
            for name, f in calls[T].items():
                t0 = time.perf_counter()
                jax.block_until_ready(f())
                times[T][name].append(time.perf_counter() - t0)
    medians = {T: {k: statistics.median(v) for k, v in d.items()} for T, d in times.items()}
    fits = {
        name: scaling.loglog_fit(args.T, [medians[T][name] for T in args.T])
        for name in calls[args.T[0]]
    }
    for T in args.T:
        print(T, {k: f"{1e3 * v:.1f} ms" for k, v in medians[T].items()})
    print({k: round(v["slope"], 3) for k, v in fits.items()}, "load", loads)
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "T": args.T,
        "reps": args.reps,
        "times_s": {str(T): d for T, d in times.items()},
        "median_s": {str(T): d for T, d in medians.items()},
        "loglog_fits": fits,
        "loadavg_1min_per_rep": loads,
    }
    pathlib.Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
