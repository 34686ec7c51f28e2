"""One-shot programs: compile time and run time of a program optimised (LLVM -O2) and one-shot.

    python benchmarks/probes/one_shot_programs.py [--calls 5] [--only NAME ...]

Each case is compiled twice in one process — as every ceemx entry point (``jit``:
``FAST_COMPILE_FLAGS``) and as a one-shot program (``jit(one_shot=True)``: also
``ONE_SHOT_COMPILE_FLAGS``, LLVM -O0 and one code-generation module) — then called alternately
``--calls`` times each (median). Compile time is lowering + XLA (``lower(...).compile()``), apart
from the steady calls; the break-even number of calls is compile saved / run time added. Cases:
the initial-state estimate of a score or prediction (``initial_state_batch``: a 50-step window
of B = 4 single-Lorenz records); the demo's data simulation (``simulate``: K = 6 coupled Lorenz,
RK4, B = 4, T = 128); the smoother (``smooth_batch``) on the single-Lorenz problem of
``compare_reference.py`` (B = 4, T = 128, n = 3), on the Figure-3 problem (K = 6, n = 18, B = 8,
T = 128), on one long record (n = 3, T = 20 000) and on K = 20 (n = 60, B = 2, T = 128); the
identifiability check's Schur complement and the per-trajectory −J on the single-Lorenz and
Figure-3 problems; the joint iteration (a hot program, for comparison). Record ``uptime``;
``XLA_FLAGS`` must not name the flags.

Backs: ``benchmarks/README.md`` ("One-shot programs": the ratios, and ``ONE_SHOT_MAX_WORK`` in
``ceemx.inference.smoother``).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

import ceemx  # noqa: E402
from ceemx.experiments import common  # noqa: E402
from ceemx.identification import schur  # noqa: E402
from ceemx.identification.problem import FitProblem, per_trajectory_nll  # noqa: E402
from ceemx.identification.solvers import joint  # noqa: E402
from ceemx.inference import smoother as sm  # noqa: E402
from ceemx.infra.compilation import jit  # noqa: E402
from ceemx.lib.tree import trace_numbers  # noqa: E402


def lorenz(K: int, B: int, T: int, coupling: bool):
    true = common.true_lorenz(
        K, key=jax.random.PRNGKey(4), coupling=coupling, integrator="midpoint"
    )
    p = common.lorenz_problem(43, true, B=B, T=T, sigma_w=0.1, sigma_v=0.5, coupling=coupling)
    system = ceemx.models.system.with_noise(p.init_system, process_noise=0.1, obs_noise=0.5)
    return system, p.data, p.states


def smoother_case(K, B, T, coupling=False):
    system, data, states = lorenz(K, B, T, coupling)
    solver = trace_numbers(ceemx.LMSmoother(max_steps=20), states.dtype)
    steps = jnp.asarray(20, jnp.int32)
    canonical = copy.copy(solver)
    object.__setattr__(canonical, "max_steps", 0)
    x0 = states + 0.5
    return sm._smooth_batch_impl, (canonical, steps, system, x0, data, False)


def problem_case(K, B, T, fn, coupling=False):
    system, data, states = lorenz(K, B, T, coupling)
    problem, theta = FitProblem.create(system, data)
    weights = jnp.ones((B,), states.dtype)
    if fn == "schur":
        return schur.schur_complement.__wrapped__, (problem, theta, states, weights)
    if fn == "nll":
        return per_trajectory_nll.__wrapped__, (problem, theta, states)
    opts = trace_numbers(ceemx.JointLM(), states.dtype)
    lam = jnp.asarray(opts.damping, states.dtype)
    return joint._iteration.__wrapped__, (opts, problem, weights, theta, states, lam)


def initial_state_case(K, B, T):
    from ceemx.evaluation import initial_state, simulation

    system, data, states = lorenz(K, B, T, False)
    solver = trace_numbers(ceemx.LMSmoother(), states.dtype)
    weak = ceemx.models.system.with_noise(system, process_noise=jnp.asarray(1.0, states.dtype))
    system, weak = simulation.strongly_typed((system, weak))
    return initial_state.initial_state_batch.__wrapped__, (solver, system, weak, data, None, True)


def simulate_case(K, B, T):
    from ceemx.data import trajectories

    true = common.true_lorenz(K, key=jax.random.PRNGKey(4), coupling=True)  # RK4, as the demo
    x0 = jnp.ones((B, true.state_dim))
    u = jnp.zeros((B, T, 0))
    fn = trajectories._simulate.__wrapped__
    return fn, (true, jax.random.PRNGKey(0), x0, u, None, true.obs_noise)


CASES = {
    "smooth_lorenz": lambda: smoother_case(1, 4, 128),
    "smooth_fig3": lambda: smoother_case(6, 8, 128, True),
    "smooth_long": lambda: smoother_case(1, 1, 20000),
    "smooth_k20": lambda: smoother_case(20, 2, 128, True),
    "schur_lorenz": lambda: problem_case(1, 4, 128, "schur"),
    "schur_fig3": lambda: problem_case(6, 8, 128, "schur", True),
    "nll_lorenz": lambda: problem_case(1, 4, 128, "nll"),
    "nll_fig3": lambda: problem_case(6, 8, 128, "nll", True),
    "iteration_lorenz": lambda: problem_case(1, 4, 128, "iteration"),
    "initial_state_lorenz": lambda: initial_state_case(1, 4, 50),
    "simulate_demo": lambda: simulate_case(6, 4, 128),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=5)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--out")
    args = ap.parse_args()
    out = {"load_before": os.getloadavg()[0], "cases": {}}
    for name, make in CASES.items():
        if args.only and name not in args.only:
            continue
        fn, fargs = make()
        compiled, compile_s = {}, {}
        for variant in ("optimised", "one_shot"):
            f = jit(fn, one_shot=variant == "one_shot")
            t = time.perf_counter()
            compiled[variant] = f.lower(*fargs).compile()
            compile_s[variant] = time.perf_counter() - t
        runs = {v: [] for v in compiled}
        for _ in range(args.calls):
            for v, c in compiled.items():
                t = time.perf_counter()
                jax.block_until_ready(c(*fargs))
                runs[v].append(time.perf_counter() - t)
        run_s = {v: statistics.median(r) for v, r in runs.items()}
        extra = run_s["one_shot"] - run_s["optimised"]
        saved = compile_s["optimised"] - compile_s["one_shot"]
        row = {
            "compile_s": compile_s,
            "run_s": run_s,
            "run_ratio": run_s["one_shot"] / run_s["optimised"],
            "break_even_calls": saved / extra if extra > 0 else float("inf"),
        }
        out["cases"][name] = row
        print(
            f"{name:18s} compile {compile_s['optimised']:6.2f} → {compile_s['one_shot']:6.2f} s   "
            f"run {run_s['optimised'] * 1e3:9.2f} → {run_s['one_shot'] * 1e3:9.2f} ms "
            f"({row['run_ratio']:.2f}×)   break-even {row['break_even_calls']:.0f} calls",
            flush=True,
        )
    out["load_after"] = os.getloadavg()[0]
    print(f"load {out['load_before']:.2f} → {out['load_after']:.2f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
