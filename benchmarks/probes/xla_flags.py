"""XLA:CPU compile options: a cold first fit against steady-state speed (issue 23, item 2).

    python benchmarks/probes/xla_flags.py [--reps 3] [--sets default,noemit,...] [--out FILE]

Each repetition runs one fresh process per option set, the sets alternated. A process sets
``XLA_FLAGS`` before JAX starts, then measures (float64, no persistent cache):

- the first single-Lorenz JointLM fit (the ``compare_reference.py`` problem, seed 43, B = 4,
  T = 128, compile included): wall and process-CPU seconds, and the backend-compile seconds JAX
  reports (``jax.monitoring``);
- that fit in steady state (median of 5 fits) and an Algorithm-1 fit of it (median of 3);
- the Figure-3 joint iteration (K = 6 coupled Lorenz, B = 8, T = 128, 342 parameters, as
  ``ceemx experiment figure3 --method joint`` builds it): median wall and CPU seconds of
  iterations 2–5.

The estimates are printed so that a set that changes them shows it. The 1-min load is recorded
before each process (the machine is shared).

Backs: ``benchmarks/README.md`` ("First-fit latency": the option sets' first fit and steady
state).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

SETS = {
    "default": "",
    "noemit": "--xla_cpu_use_fusion_emitters=false",
    "split1": "--xla_cpu_parallel_codegen_split_count=1",
    "noexp": "--xla_llvm_disable_expensive_passes=true",
    "noemit_split1": "--xla_cpu_use_fusion_emitters=false --xla_cpu_parallel_codegen_split_count=1",
    "noemit_O1": "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=1",
    "tests": "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 "
    "--xla_cpu_parallel_codegen_split_count=1",
}

CHILD = r"""
import json, resource, statistics, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from jax._src import monitoring
compile_s = [0.0]
def listen(event, duration, **kw):
    if event.endswith("backend_compile_duration"):
        compile_s[0] += duration
monitoring.register_event_duration_secs_listener(listen)
import jax.numpy as jnp
import ceemx
from ceemx.experiments import common, figure3
from ceemx.models import with_noise

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

out = {}
true = common.true_lorenz(1, key=jax.random.PRNGKey(4), m=2, coupling=False, integrator="midpoint")
p = common.lorenz_problem(43, true, B=4, T=128, sigma_w=0.1, sigma_v=0.5, coupling=False,
                          x1_std=5 ** 0.5)
guess = with_noise(p.init_system, 0.1, 0.5)
data = ceemx.Trajectories(jnp.asarray(p.data.y))
def one(solver):
    r = ceemx.fit(guess, data, solver=solver, trainable=common.LORENZ_PARAMS, progress=False)
    r.states.block_until_ready()
    return r
t, c = time.perf_counter(), cpu()
r = one(ceemx.JointLM())
out["first_fit_s"], out["first_fit_cpu_s"] = time.perf_counter() - t, cpu() - c
out["first_fit_backend_compile_s"] = compile_s[0]
out["estimate"] = [float(r.system.sigma[0]), float(r.system.rho[0]), float(r.system.beta[0])]
ts = []
for _ in range(5):
    t = time.perf_counter(); one(ceemx.JointLM()); ts.append(time.perf_counter() - t)
out["steady_joint_fit_s"] = statistics.median(ts)
one(ceemx.Alternating())
ts = []
for _ in range(3):
    t = time.perf_counter(); one(ceemx.Alternating()); ts.append(time.perf_counter() - t)
out["steady_alternating_fit_s"] = statistics.median(ts)
true6 = common.true_lorenz(6, key=jax.random.PRNGKey(4), obs_noise=figure3.SIGMA_V)
p6 = common.lorenz_problem(42, true6, B=8, T=128, sigma_w=0.0, sigma_v=figure3.SIGMA_V,
                           coupling=True)
pn, on, rho_x = figure3.fit_setup("paper")
walls, cpus = [], []
mark = [time.perf_counter(), cpu()]
def cb(info):
    now = [time.perf_counter(), cpu()]
    walls.append(now[0] - mark[0]); cpus.append(now[1] - mark[1])
    mark[:] = [time.perf_counter(), cpu()]
mark[:] = [time.perf_counter(), cpu()]
r6 = ceemx.fit(with_noise(p6.init_system, pn, on), p6.data, figure3._noisy_states(p6, 42),
               solver=common.make_solver("joint", rho_x=rho_x, rtol=1e-10),
               trainable=common.LORENZ_PARAMS_H, max_epochs=5, callbacks=[cb], progress=False)
out["fig3_first_iteration_s"] = walls[0]
out["fig3_iteration_s"] = statistics.median(walls[1:])
out["fig3_iteration_cpu_s"] = statistics.median(cpus[1:])
out["fig3_J"] = r6.history[-1]["J"]
print("RESULT" + json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--src", default=None, help="PYTHONPATH of the ceemx to measure")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    names = args.sets.split(",")
    runs = []
    for rep in range(args.reps):
        for name in names:
            env = dict(os.environ, XLA_FLAGS=SETS[name], CEEMX_COMPILATION_CACHE="off")
            if args.src:
                env["PYTHONPATH"] = args.src
            load = os.getloadavg()[0]
            proc = subprocess.run(
                [sys.executable, "-c", CHILD], env=env, capture_output=True, text=True
            )
            line = [s for s in proc.stdout.splitlines() if s.startswith("RESULT")]
            if not line:
                print(proc.stderr[-3000:])
                continue
            rec = {"set": name, "rep": rep, "load_before": load, **json.loads(line[0][6:])}
            runs.append(rec)
            print(json.dumps(rec), flush=True)
    summary = {}
    for name in names:
        rs = [r for r in runs if r["set"] == name]
        if rs:
            keys = [k for k, v in rs[0].items() if isinstance(v, float) and k != "load_before"]
            summary[name] = {k: statistics.median(r[k] for r in rs) for k in keys}
    print(json.dumps(summary, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(
                {
                    "date": time.strftime("%Y-%m-%d %H:%M"),
                    "sets": SETS,
                    "runs": runs,
                    "summary": summary,
                },
                f,
                indent=1,
            )


if __name__ == "__main__":
    main()
