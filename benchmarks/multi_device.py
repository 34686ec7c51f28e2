"""Trajectory-axis data parallelism (``fit(devices="all")``): time per device count.

Usage::

    python benchmarks/multi_device.py [--smoke] [--out benchmarks/results/multi_device.json]

For each device count (1, 2, 4; ``--smoke``: 1, 2 with tiny sizes) a fresh subprocess starts with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (set before JAX starts) and, on a K = 2
coupled-Lorenz problem (B = 16, T = 128; float64), times in steady state

* one :class:`ceemx.JointLM` iteration of ``ceemx.fit(..., devices="all")``: a fit of 5 epochs
  that cannot converge; the first two epochs compile (the second takes another code path), the
  median of the last 3 is reported;
* one :func:`ceemx.smooth` call on the data and states placed by
  :func:`ceemx.data.sharding.shard_batch` (run once to compile, then the median of 3).

It checks that the states really lie on N devices and that J after the fit agrees across device
counts. The 1-minute load average (``uptime``) is recorded before every run. Forced host devices
share the machine's CPU cores, so on a small machine expect no speed-up: this measures the
partitioning overhead and checks that the sharded program runs and agrees; on several GPUs or
hosts the same code spreads the trajectories over real devices.

Writes ``benchmarks/results/multi_device.json``. Backs: ``benchmarks/README.md`` (several
devices).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, statistics, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ceemx
from ceemx.experiments import common
from ceemx.data.sharding import batch_mesh, shard_batch

n, K, B, T = (int(a) for a in sys.argv[1:5])
assert len(jax.devices()) == n, jax.devices()
true = common.true_lorenz(K, process_noise=0.01, obs_noise=0.01)
p = common.lorenz_problem(0, true, B=B, T=T, sigma_w=0.01, sigma_v=0.01)
x0 = p.states  # the simulated states: no warm-start compile in the timed child

solver = ceemx.JointLM(rtol=0.0, atol=0.0)  # all epochs (a tie at exactly 0 aside)
res = ceemx.fit(p.init_system, p.data, x0, solver=solver, trainable=common.LORENZ_PARAMS_H,
                max_epochs=5, outliers="keep", progress=False, devices="all")
epoch_times = [h["time"] for h in res.history]
fit_devices = len(res.states.sharding.device_set)

data, xs = shard_batch(p.data, x0, batch_mesh())
smooth = lambda: jax.block_until_ready(ceemx.smooth(p.init_system, data, xs).states)
t0 = time.perf_counter(); out = smooth(); first = time.perf_counter() - t0
times = []
for _ in range(3):
    t0 = time.perf_counter(); out = smooth(); times.append(time.perf_counter() - t0)
print(json.dumps({
    "devices": n, "fit_devices": fit_devices, "smooth_devices": len(out.sharding.device_set),
    "fit_first_s": epoch_times[0] + epoch_times[1],
    "fit_steady_s": statistics.median(epoch_times[2:]),
    "fit_epoch_s": epoch_times, "smooth_first_s": first,
    "smooth_steady_s": statistics.median(times), "smooth_s": times,
    "J": [h["J"] for h in res.history],
}))
"""


def run_one(n: int, K: int, B: int, T: int) -> dict:
    flags = os.environ.get("XLA_FLAGS", "")
    env = dict(os.environ, XLA_FLAGS=f"{flags} --xla_force_host_platform_device_count={n}".strip())
    load = os.getloadavg()[0]
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(n), str(K), str(B), str(T)],
        env=env,
        capture_output=True,
        text=True,
    )
    if out.returncode != 0:
        raise RuntimeError(f"{n} devices failed:\n{out.stderr[-4000:]}")
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    rec["load"] = load
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes, 1 and 2 devices (< 60 s)")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/...)")
    args = ap.parse_args()
    if args.smoke:
        counts, K, B, T = (1, 2), 1, 4, 16
    else:
        counts, K, B, T = (1, 2, 4), 2, 16, 128
    out = args.out or os.path.join(os.path.dirname(__file__), "results", "multi_device.json")
    print(f"K = {K}, B = {B}, T = {T}, float64, JointLM; steady state = median of 3 after compile")
    head = f"{'devices':>7} {'used':>4} {'fit iter s':>10} {'smooth s':>9} {'compile+1st s':>13}"
    print(f"{head} {'load':>5}  J after 5 epochs", flush=True)
    runs = []
    for n in counts:
        rec = run_one(n, K, B, T)
        runs.append(rec)
        first = rec["fit_first_s"] + rec["smooth_first_s"]
        print(
            f"{n:>7} {rec['fit_devices']:>4} {rec['fit_steady_s']:>10.3f} "
            f"{rec['smooth_steady_s']:>9.3f} {first:>13.1f} {rec['load']:>5.2f}  "
            f"{rec['J'][-1]:.12g}",
            flush=True,
        )
    J = [r["J"][-1] for r in runs]
    spread = max(abs(j - J[0]) for j in J) / abs(J[0])
    print(f"relative spread of J across device counts: {spread:.1e}")
    ok = all(r["fit_devices"] == r["devices"] == r["smooth_devices"] for r in runs)
    if not ok:
        print("WARNING: some run did not use all its devices")
    summary = {
        "smoke": args.smoke,
        "K": K,
        "B": B,
        "T": T,
        "cpu_count": os.cpu_count(),
        "J_relative_spread": spread,
        "runs": runs,
    }
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as f:
        json.dump(summary, f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
