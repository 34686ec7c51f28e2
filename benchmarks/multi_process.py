"""One fit as two processes (``jax.distributed``, Gloo CPU collectives) against one process.

Usage::

    python benchmarks/multi_process.py [--smoke] [--rounds 2] [--out FILE.json]

Each round runs the same child program once as one process and once as two local processes
(``ceemx.infra.distributed.launch``; the order alternates between rounds), on the same data: a
K = 2 coupled-Lorenz problem (B = 16, T = 128, float64; ``--smoke``: K = 1, B = 4, T = 16), a
:class:`ceemx.JointLM` fit of 6 epochs that cannot converge (``rtol = atol = 0``) with
``devices="all"`` — one device per process, so the two-process run splits the trajectories 8 + 8
over the processes. Reported per run: the first two epochs (they compile) and the median of the
last 4 epoch times (steady state), and the whole fit's wall time; over the rounds the median. It
checks that θ and J after the fit agree between one and two processes (relative difference). The
1-minute load average is recorded before every run.

On the 2-core development machine the two processes share the cores with each other (and with
other users' jobs), and every epoch adds the cross-process all-reduces and host gathers over TCP:
expect no speed-up there; the point is that it runs and agrees. On several hosts each process has
its own cores.

Writes ``benchmarks/results/multi_process.json``. Backs: ``benchmarks/README.md`` (several
processes).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from ceemx.infra import distributed

CHILD = r"""
import json, sys, time
from ceemx.infra import distributed
distributed.initialize()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ceemx
from ceemx.experiments import common

K, B, T, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
true = common.true_lorenz(K, process_noise=0.01, obs_noise=0.01)
p = common.lorenz_problem(0, true, B=B, T=T, sigma_w=0.01, sigma_v=0.01)
t0 = time.perf_counter()
res = ceemx.fit(p.init_system, p.data, p.states, solver=ceemx.JointLM(rtol=0.0, atol=0.0),
                trainable=common.LORENZ_PARAMS_H, max_epochs=6, outliers="keep",
                progress=False, devices="all")
wall = time.perf_counter() - t0
if distributed.is_main_process():
    with open(out, "w") as f:
        json.dump({"processes": jax.process_count(), "devices": len(jax.devices()),
                   "epoch_s": [h["time"] for h in res.history], "fit_s": wall,
                   "J": [h["J"] for h in res.history],
                   "theta": np.asarray(res.theta).tolist()}, f)
"""


def run(processes: int, K: int, B: int, T: int, folder: str, timeout: float) -> dict:
    """One run of the child as ``processes`` processes; its record with the load before it."""
    script = os.path.join(folder, "child.py")
    with open(script, "w") as f:
        f.write(CHILD)
    out = os.path.join(folder, f"out{processes}.json")
    if os.path.exists(out):
        os.remove(out)
    load = os.getloadavg()[0]
    command = [sys.executable, script, str(K), str(B), str(T), out]
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in (distributed.ENV_COORDINATOR, distributed.ENV_NUM_PROCESSES)
    }
    env.pop(distributed.ENV_PROCESS_ID, None)
    t0 = time.perf_counter()
    if processes == 1:
        codes = [subprocess.run(command, env=env, timeout=timeout).returncode]
    else:
        codes = distributed.launch(command, processes, timeout=timeout, env=env)
    wall = time.perf_counter() - t0
    if any(codes):
        raise RuntimeError(f"{processes} process(es) failed: exit codes {codes}")
    with open(out) as f:
        rec = json.load(f)
    epochs = rec["epoch_s"]
    rec.update(
        load=load,
        wall_s=wall,
        first_two_s=epochs[0] + epochs[1],
        steady_s=statistics.median(epochs[2:]),
    )
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="tiny sizes, one round (< 3 min)")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of (1, 2) processes (2)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per run (900)")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/...)")
    args = ap.parse_args()
    K, B, T = (1, 4, 16) if args.smoke else (2, 16, 128)
    rounds = 1 if args.smoke else args.rounds
    out = args.out or os.path.join(os.path.dirname(__file__), "results", "multi_process.json")
    print(f"K = {K}, B = {B}, T = {T}, float64, JointLM 6 epochs; {rounds} round(s)")
    print(f"{'procs':>5} {'epoch s':>8} {'first 2 s':>9} {'fit s':>7} {'run s':>7} {'load':>5}")
    runs: list[dict] = []
    with tempfile.TemporaryDirectory() as folder:
        for r in range(rounds):
            for n in (1, 2) if r % 2 == 0 else (2, 1):
                rec = run(n, K, B, T, folder, args.timeout)
                rec["round"] = r
                runs.append(rec)
                print(
                    f"{n:>5} {rec['steady_s']:>8.3f} {rec['first_two_s']:>9.1f} "
                    f"{rec['fit_s']:>7.1f} {rec['wall_s']:>7.1f} {rec['load']:>5.2f}",
                    flush=True,
                )

    def med(n: int, key: str) -> float:
        return statistics.median(x[key] for x in runs if x["processes"] == n)

    one = next(x for x in runs if x["processes"] == 1)
    two = next(x for x in runs if x["processes"] == 2)
    rel = lambda a, b: max(abs(p - q) for p, q in zip(a, b, strict=True)) / max(map(abs, b))  # noqa: E731
    theta_diff, J_diff = rel(two["theta"], one["theta"]), rel(two["J"], one["J"])
    summary = {
        "smoke": args.smoke,
        "K": K,
        "B": B,
        "T": T,
        "cpu_count": os.cpu_count(),
        "median_steady_s": {"1": med(1, "steady_s"), "2": med(2, "steady_s")},
        "median_fit_s": {"1": med(1, "fit_s"), "2": med(2, "fit_s")},
        "theta_relative_difference": theta_diff,
        "J_relative_difference": J_diff,
        "runs": runs,
    }
    print(
        f"median steady epoch: 1 process {summary['median_steady_s']['1']:.3f} s, 2 processes "
        f"{summary['median_steady_s']['2']:.3f} s; θ differs by {theta_diff:.1e}, J by "
        f"{J_diff:.1e} (relative)"
    )
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as f:
        json.dump(summary, f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
