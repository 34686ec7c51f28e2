"""Joint iteration time on the Figure-3 B = 8 seed-42 problem, for two source trees (before/after).

Usage::

    python benchmarks/joint_iteration_before_after.py --src OLD/src --src NEW/src \
        [--repeats 3] [--count] [--out FILE]

The problem is built by each tree's own ``ceemx.experiments.common`` exactly as
``ceemx experiment figure3 --method joint`` builds its B = 8, seed-42 run: K = 6 coupled Lorenz,
T = 128, σ_v = 0.01, paper weighting (unit noise scales, ρ_x = 5·10⁻⁵), θ·(1 + U(−0.1, 0.1)) with
H trainable, states from the truth + N(0, 1), rtol = 1e-10 (the run stops after 6 iterations).
It works with the API before issue 7 (``fit(..., method="joint", smoother=LMSmoother(rho_x))``)
and after it (``fit(..., solver=JointLM(rho_x=...))``).

Each repeat runs one fresh subprocess per tree, alternating between the trees; the 1-min load
average is recorded before every run. Per run: the wall and process-CPU time of every iteration
(callback to callback); "first" includes JIT compilation, "steady" is the median of the later
iterations, compile = first − steady. ``--count`` adds one (untimed) run per tree that counts
evaluations of the joint objective + linearisation (the solver's ``evaluate``) with
``jax.debug.callback``.

Backs: ``benchmarks/README.md`` ("Joint iteration before/after the carried linearisation":
"**1.23× faster per iteration** (0.816 → 0.664 s") and ``docs/results.md`` ("The joint iteration
is 1.23× faster in steady state"). Runs on trees from before and after the package folders
(b271a33), so the documented pair 36ce59f / 1dafde2 still works.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

CHILD = r"""
import json, sys, time
import jax
import jax.numpy as jnp
import ceemx
from ceemx.experiments import common, figure3

count = sys.argv[1] == "count"
common.enable_x64()
new_api = hasattr(ceemx, "JointLM") and hasattr(ceemx, "Alternating")
calls = [0]
if count:  # wrap the joint evaluate (objective + linearisation) with a host-side counter
    if new_api:
        try:
            import ceemx.identification.schur as jm

            name = "joint_evaluator"
        except ImportError:  # a tree before the Schur module
            try:
                import ceemx.identification.solvers.joint as jm
            except ImportError:  # a tree before the package folders (b271a33)
                import ceemx.solvers.joint as jm
            name = "_evaluator"
    else:
        import ceemx.joint as jm
        name = "_joint_evaluate"
    raw = getattr(jm, name)

    def wrapped(*a, **k):
        ev = raw(*a, **k)

        def counted(z):
            jax.debug.callback(lambda: calls.__setitem__(0, calls[0] + 1))
            return ev(z)

        return counted

    setattr(jm, name, wrapped)

seed, B = 42, 8
true = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=figure3.SIGMA_V)
problem = common.lorenz_problem(seed, true, B=B, T=128, sigma_w=0.0, sigma_v=figure3.SIGMA_V,
                                coupling=True)
pn, on, rho_x = figure3.fit_setup("paper")
if new_api:
    from ceemx.models import with_noise
    system = with_noise(problem.init_system, pn, on)
    kw = dict(solver=common.make_solver("joint", rho_x=rho_x, rtol=1e-10))
else:
    system = common.with_noise(problem.init_system, pn, on)
    kw = dict(method="joint", smoother=ceemx.LMSmoother(rho_x=rho_x), tol=1e-10)
k_x = jax.random.fold_in(jax.random.PRNGKey(seed), 1)
x_init = problem.states + jax.random.normal(k_x, problem.states.shape, problem.states.dtype)
jax.block_until_ready((system, x_init, problem.data))
stamps, cpu, counts = [], [], [0]

def cb(info):
    stamps.append(time.perf_counter())
    cpu.append(time.process_time())
    counts.append(calls[0])

cpu.append(time.process_time())
stamps.append(time.perf_counter())
res = ceemx.fit(system, problem.data, x_init, trainable=common.LORENZ_PARAMS_H, max_epochs=200,
                callbacks=[cb], progress=False, **kw)
times = [b - a for a, b in zip(stamps[:-1], stamps[1:])]
cpu_times = [b - a for a, b in zip(cpu[:-1], cpu[1:])]
try:
    from ceemx.evaluation import metrics as ev
except ImportError:  # the module before b271a33
    from ceemx import evaluate as ev
print(json.dumps({
    "file": ceemx.__file__,
    "times": times,
    "cpu_times": cpu_times,
    "evaluations": [b - a for a, b in zip(counts[:-1], counts[1:])] if count else None,
    "J": [h["J"] for h in res.history],
    "trials": [h.get("trials", h.get("learner_steps")) for h in res.history],
    "eps": float(ev.dynamics_error(res.system, true)),
}))
"""


def run_one(src: str, mode: str) -> dict:
    env = dict(os.environ, PYTHONPATH=os.path.abspath(src))
    load = os.getloadavg()
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode], env=env, capture_output=True, text=True, check=True
    )
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec["load"] = load
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", action="append", required=True, help="a source tree (repeatable)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--count", action="store_true", help="also count evaluations (untimed run)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    runs: dict[str, list[dict]] = {s: [] for s in args.src}
    for r in range(args.repeats):
        for src in args.src:
            rec = run_one(src, "time")
            runs[src].append(rec)
            steady = statistics.median(rec["times"][1:])
            steady_cpu = statistics.median(rec["cpu_times"][1:])
            print(
                f"[{r}] {src}: load {rec['load'][0]:.2f}; first {rec['times'][0]:.2f} s, "
                f"steady {steady:.3f} s/iter (CPU {steady_cpu:.3f} s), "
                f"{len(rec['times'])} iterations, "
                f"trials {rec['trials']}, ε {rec['eps']:.4g} ({rec['file']})",
                flush=True,
            )
    counted = {}
    if args.count:
        for src in args.src:
            rec = run_one(src, "count")
            counted[src] = rec
            print(
                f"{src}: evaluations per iteration {rec['evaluations']}, trials {rec['trials']}",
                flush=True,
            )
    summary = {}
    for src, recs in runs.items():
        steady = [statistics.median(x["times"][1:]) for x in recs]
        first = [x["times"][0] for x in recs]
        cpu = [statistics.median(x["cpu_times"][1:]) for x in recs]
        summary[src] = {
            "steady_cpu_median_s": statistics.median(cpu),
            "steady_cpu": cpu,
            "steady_median_s": statistics.median(steady),
            "steady": steady,
            "first_median_s": statistics.median(first),
            "compile_median_s": statistics.median(
                f - s for f, s in zip(first, steady, strict=True)
            ),
            "first": first,
            "J": recs[0]["J"],
            "eps": recs[0]["eps"],
            "loads": [x["load"][0] for x in recs],
        }
        s = summary[src]
        print(
            f"{src}: steady {s['steady_median_s']:.3f} s/iter (runs "
            f"{', '.join(f'{t:.3f}' for t in steady)}), first iteration "
            f"{s['first_median_s']:.2f} s (compile ≈ {s['compile_median_s']:.2f} s), "
            f"J final {s['J'][-1]:.10g}, ε {s['eps']:.4g}"
        )
    if len(args.src) == 2:
        a, b = (summary[s]["steady_median_s"] for s in args.src)
        print(f"ratio steady {args.src[0]} / {args.src[1]}: {a / b:.2f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"runs": runs, "counted": counted, "summary": summary}, f, indent=2)


if __name__ == "__main__":
    main()
