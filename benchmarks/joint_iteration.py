"""Steady-state time of one joint (x, θ) iteration on the Figure-3 B = 8 problem, side by side.

Usage::

    python benchmarks/joint_iteration.py --src OLD/src --src NEW/src [--repeats 3] [--out FILE]

Each repeat runs one fresh subprocess per source tree, alternating between them, so both see the
same machine load. A run fits K = 6 coupled Lorenz attractors (n = 18, m = 16, 342 parameters:
σ, ρ, β per attractor and H), B = 8, T = 128, paper weighting (unit noise scales, ρ_x = 5·10⁻⁵)
from the true states + N(0, 1) for ``--iterations`` joint iterations and records the wall time of
every iteration. The first iteration includes JIT compilation and is reported apart; "steady" is
the median of the later ones. The load average is recorded before every run.
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
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import ceemx
from ceemx.systems import CoupledLorenz, initial_states, random_coupling, random_observation_matrix

K, B, T, iters = 6, 8, 128, int(sys.argv[1])
kc, kh = jax.random.split(jax.random.PRNGKey(4))
C = random_observation_matrix(kc, K)
H = random_coupling(kh, K)
ones = jnp.ones((K,))
true = CoupledLorenz(10 * ones, 28 * ones, 8 / 3 * ones, C, H=H, dt=0.04,
                     process_noise=1.0, obs_noise=1.0)
k_x1, k_sim, k_theta, k_x = jax.random.split(jax.random.PRNGKey(42), 4)
xs, data = ceemx.simulate(true, k_sim, initial_states(k_x1, B, K), T, process_noise=False,
                          obs_noise=ceemx.DiagonalGaussian(0.01, true.obs_dim))
where = lambda s: (s.sigma, s.rho, s.beta, s.H)
leaves = where(true)
keys = jax.random.split(k_theta, len(leaves))
guess = jax.tree_util.tree_map(lambda a: a, true)
import equinox as eqx
guess = eqx.tree_at(where, true, tuple(a * (1 + jax.random.uniform(k, a.shape, a.dtype, -0.1, 0.1))
                                       for k, a in zip(keys, leaves)))
x0 = xs + jax.random.normal(k_x, xs.shape, xs.dtype)
stamps = [time.perf_counter()]
cb = lambda info: stamps.append(time.perf_counter())
if hasattr(ceemx, "Alternating"):
    kw = dict(solver=ceemx.JointLM(rho_x=0.5 * 0.01**2, rtol=0.0, atol=-1e300))
else:
    kw = dict(method="joint", smoother=ceemx.LMSmoother(rho_x=0.5 * 0.01**2), tol=0.0,
              atol=-1e300)
stamps[0] = time.perf_counter()
res = ceemx.fit(guess, data, x0, trainable=where, max_epochs=iters, callbacks=[cb],
                progress=False, **kw)
times = [b - a for a, b in zip(stamps[:-1], stamps[1:])]
print(json.dumps({"times": times, "J": [h["J"] for h in res.history],
                  "trials": [h.get("trials", h.get("learner_steps")) for h in res.history]}))
"""


def run_one(src: str, iterations: int) -> dict:
    env = dict(os.environ, PYTHONPATH=os.path.abspath(src))
    load = os.getloadavg()[0]
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(iterations)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec["load"] = load
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", action="append", required=True, help="a source tree (repeatable)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    runs: dict[str, list[dict]] = {s: [] for s in args.src}
    for r in range(args.repeats):
        for src in args.src:
            rec = run_one(src, args.iterations)
            runs[src].append(rec)
            steady = statistics.median(rec["times"][1:])
            print(
                f"[{r}] {src}: first {rec['times'][0]:.2f} s, steady {steady:.3f} s/iter, "
                f"trials {rec['trials']}, load {rec['load']:.2f}",
                flush=True,
            )
    summary = {}
    for src, recs in runs.items():
        steady = [statistics.median(x["times"][1:]) for x in recs]
        first = [x["times"][0] for x in recs]
        summary[src] = {
            "steady_median_s": statistics.median(steady),
            "steady": steady,
            "first_median_s": statistics.median(first),
            "first": first,
            "J_final": recs[0]["J"][-1],
            "loads": [x["load"] for x in recs],
        }
        print(
            f"{src}: steady {summary[src]['steady_median_s']:.3f} s/iter (runs {steady}), "
            f"first iteration (compile) {summary[src]['first_median_s']:.2f} s, "
            f"J final {summary[src]['J_final']:.10g}"
        )
    if len(args.src) == 2:
        a, b = (summary[s]["steady_median_s"] for s in args.src)
        print(f"ratio {args.src[0]} / {args.src[1]}: {a / b:.2f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"runs": runs, "summary": summary}, f, indent=2)


if __name__ == "__main__":
    main()
